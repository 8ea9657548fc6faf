"""``sgmodel bench predict``: one stereo pair to a 3DGS scene in a warm process, split by stage.

What ``sgmodel predict`` does for one pair once the process is warm (CUDA context, cuDNN plans and the
rasteriser's kernels loaded, the model on the device): encoder, decoder + predictor, composer, the
``.ply`` export and the rendering of one novel view, each synchronised; medians of ``--repeats`` pairs
after ``--warmup``. A cold ``sgmodel predict`` adds the process start, the model load and the first
launches (its own table says how long each took). The pair is synthetic (smooth random texture shifted by
a few pixels) at ``--size``; with ``--checkpoint`` the trained model runs, else a fresh one of the given
flags (the time does not depend on the weights).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import torch

from scenesplat_stereo.text import argtype, markdown_table, parse_size

from .. import export
from ..args import add_model_arguments, params_from_args
from ..geometry import depth_from_disparity
from ..model import create_model, load_predictor
from ..render import render_views
from . import report, synced_clock

STAGES = ("encoder", "decoder + predictor", "composer", "export .ply", "render one view")


def synthetic_pair(width: int, height: int, device: torch.device) -> tuple[torch.Tensor, ...]:
    """(left, right [1,3,H,W] in [0,1], K [1,3,3], baseline [1] metres): smooth texture, 4 px disparity."""
    g = torch.Generator().manual_seed(0)
    low = torch.rand(1, 3, max(2, height // 16), max(2, width // 16), generator=g)
    left = torch.nn.functional.interpolate(low, size=(height, width), mode="bicubic", align_corners=False).clamp(0, 1)
    f = 0.9 * max(width, height)
    K = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]])
    return (left.to(device), torch.roll(left, -4, -1).to(device), K.to(device), torch.tensor([0.1], device=device))


def run(args: argparse.Namespace) -> int:
    device = torch.device(args.device)
    if args.checkpoint:
        model = load_predictor(args.checkpoint, device, args.encoder_weights, args.encoder_repo, args.encoder).model
    else:
        model = create_model(params_from_args(args)[0], device).eval()
    width, height = args.size
    left, right, K, baseline = synthetic_pair(width, height, device)
    viewmat = torch.eye(4, device=device)[None, None].clone()
    viewmat[..., 0, 3] = -0.05

    now = synced_clock(device)
    times: dict[str, list[float]] = {s: [] for s in STAGES}
    with torch.no_grad(), tempfile.TemporaryDirectory() as tmp:
        for i in range(args.warmup + args.repeats):
            t = [now()]
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=device.type == "cuda"):
                disparity, features = model.encode(left, right)
                z = depth_from_disparity(disparity, K[:, 0, 0], baseline)
                t.append(now())
                front, back, dz, c = model.layers(left, z, features, K)
                t.append(now())
            gaussians = model.compose(front, back, dz, c, baseline)
            t.append(now())
            export.write_ply(gaussians, Path(tmp) / "scene.ply")
            t.append(now())
            render_views(gaussians, viewmat, K[:, None], width, height)
            t.append(now())
            if i >= args.warmup:
                for stage, a, b in zip(STAGES, t, t[1:]):
                    times[stage].append(b - a)
    med = {s: statistics.median(v) * 1e3 for s, v in times.items()}
    rows = [[s, f"{med[s]:.1f}"] for s in STAGES]
    rows += [["**prediction** (encoder to Gaussians)", f"{sum(med[s] for s in STAGES[:3]):.1f}"],
             ["**total**", f"{sum(med.values()):.1f}"]]
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    n = next(iter(gaussians.values())).shape[1]
    report(f"One pair of {width}x{height} to {n:,} Gaussians in a warm process on {name} "
           f"({'checkpoint ' + str(args.checkpoint) if args.checkpoint else 'fresh model'}, encoder "
           f"{model.params.encoder.name}); medians of {args.repeats} pairs after {args.warmup} warm-up.\n\n"
           f"{markdown_table(['stage', 'median ms'], rows)}\n", args.out)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    p.add_argument("--checkpoint", help="a trained model (default: a fresh one of the model flags)")
    p.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    p.add_argument("--size", type=argtype(parse_size, "--size"), default=(320, 256),
                   help="input pair size WxH, multiples of 16 (default 320x256)")
    p.add_argument("--warmup", type=int, default=3, help="untimed pairs first (default 3)")
    p.add_argument("--repeats", type=int, default=10, help="timed pairs (default 10)")
    p.add_argument("--out", type=Path, help="also write the markdown table here")
