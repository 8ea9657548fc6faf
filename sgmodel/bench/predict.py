"""``sgmodel bench predict``: one pair to a scene by stage, or (``--video``) a stereo video's pairs/s and latency.

``--video`` is described in ``sgmodel.bench.predict_video``.

What ``sgmodel predict`` does for one pair once the process is warm (CUDA context, cuDNN plans and the
rasteriser's kernels loaded, the model on the device): encoder, decoder + predictor, composer, the scene
to the host (Gaussians without a stereo depth dropped, SH cut to the content's degree), the ``.ply`` write
(as predict writes it: atomic, no fsync) and the rendering of one novel view, each synchronised; medians
of ``--repeats`` pairs after ``--warmup``. A second table times every scene format's write (and the ``.ply``
with fsync, and the ``.spz``'s deflate alone) with its size (``scenesplat_stereo.bench.scenes.writer_rows``).
A cold ``sgmodel predict`` adds the process start, the model load and the first launches (its own table says
how long each took). The pair is synthetic (smooth random texture shifted by a few pixels) at ``--size``;
with ``--checkpoint`` the trained model runs, else a fresh one of the given flags (the time does not depend
on the weights). The model runs in float32, as ``sgmodel predict`` does (``--amp``: bf16 autocast on CUDA,
as trained).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.bench.scenes import COLUMNS, writer_rows
from scenesplat_stereo.common.measure import synced_clock
from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import argtype, markdown_table, parse_size, whole_number
from scenesplat_stereo.scene.gaussians import GaussianScene
from scenesplat_stereo.scene.scene_files import FORMATS
from sgmodel.args import (add_device_argument, add_model_arguments, add_precision_argument, device_from_flag,
                          params_from_args)
from sgmodel.bench import describe, report, synthetic_pair
from sgmodel.model.geometry import depth_from_disparity
from sgmodel.model.layers import amp_autocast
from sgmodel.model.network import Predictor, create_model, load_predictor
from sgmodel.model.render import SH_DEGREE, render_views
from sgmodel.predict import export
from sgmodel.predict.scene_writers import write_scene
from sgmodel.predict.video import SCENE_WRITERS
from sgmodel.weights import SHIPPED, checkpoint_path

OWNER = "sgmodel bench predict"  # recorded beside --out (a pair or --video): a later run may replace its own report
STAGES = ("encoder", "decoder + predictor", "composer", "scene to host", "write .ply", "render one view")


def bench_model(args: argparse.Namespace, device: torch.device) -> Predictor:
    """The trained model of ``--checkpoint`` or a fresh one of the model flags, ready for inference."""
    if args.checkpoint:
        return load_predictor(checkpoint_path(args.checkpoint), device, args.encoder_weights, args.encoder_repo,
                              args.encoder, args.amp)
    return Predictor(create_model(params_from_args(args)[0], device), amp=args.amp)


def run(args: argparse.Namespace) -> int:
    out = OwnedFile(args.out, "--out", OWNER)  # before any work
    device = torch.device(device_from_flag(args.device))
    predictor = bench_model(args, device)
    if args.video:
        from sgmodel.bench.predict_video import bench_video

        return bench_video(args, predictor, device, out)
    model = predictor.model
    width, height = args.size
    left, right, K, baseline = synthetic_pair(width, height, device)
    viewmat = torch.eye(4, device=device)[None, None].clone()
    viewmat[..., 0, 3] = -0.05

    now = synced_clock(device)
    times: dict[str, list[float]] = {s: [] for s in STAGES}
    with torch.no_grad(), tempfile.TemporaryDirectory() as tmp:
        for i in range(args.warmup + args.repeats):
            t = [now()]
            with amp_autocast(left, predictor.amp):
                disparity, features = model.encode(left, right)
                z = depth_from_disparity(disparity, K[:, 0, 0], baseline)
                t.append(now())
                front, back, dz, c = model.layers(left, z, features, K)
                t.append(now())
            gaussians = model.compose(front, back, dz, c, baseline)
            t.append(now())
            scene = export.to_scene(gaussians, 0, model.validity(disparity, K, baseline)[1][0])
            t.append(now())
            write_scene(scene, Path(tmp) / "scene.ply")
            t.append(now())
            render_views(gaussians, viewmat, K[:, None], width, height)
            t.append(now())
            if i >= args.warmup:
                for stage, a, b in zip(STAGES, t, t[1:]):
                    times[stage].append(b - a)
        formats = export_times(scene, Path(tmp), args.warmup, args.repeats)
    med = {s: statistics.median(v) * 1e3 for s, v in times.items()}
    rows = [[s, f"{med[s]:.1f}"] for s in STAGES]
    rows += [["**prediction** (encoder to Gaussians)", f"{sum(med[s] for s in STAGES[:3]):.1f}"],
             ["**total**", f"{sum(med.values()):.1f}"]]
    n = next(iter(gaussians.values())).shape[1]
    report(f"One pair of {width}x{height} to {n:,} Gaussians ({len(scene):,} with a stereo depth, SH degree "
           f"{scene.sh_degree}) in a warm process on {describe(args, predictor, device)}; medians of {args.repeats} "
           f"pairs after {args.warmup} warm-up.\n\n"
           f"{markdown_table(['stage', 'median ms'], rows)}\n\n"
           f"Writing that scene ({len(scene):,} Gaussians) in each format, median of {args.repeats}:\n\n"
           f"{markdown_table(COLUMNS, formats)}\n", out)
    return 0


def export_times(scene: GaussianScene, folder: Path, warmup: int, repeats: int) -> list[list[str]]:
    """Rows (``scenesplat_stereo.bench.scenes.COLUMNS``) of writing ``scene`` with every writer as predict does
    (atomic, no fsync), the ``.ply`` with fsync and the ``.spz``'s deflate alone (``writer_rows``). When the
    prediction has no higher SH (a fresh model's SH heads start at zero), the same Gaussians with degree-2 SH
    as a trained model predicts are timed too (coefficients drawn from N(0, 0.02^2): sizes of incompressible
    values)."""
    scenes = [(f"as predicted ({scene.sh_degree})", scene)]
    if scene.sh_degree < SH_DEGREE:
        rng = np.random.default_rng(0)
        rest = rng.normal(0, 0.02, (len(scene), (SH_DEGREE + 1) ** 2 - scene.sh.shape[1], 3)).astype(np.float32)
        scenes.append((f"{SH_DEGREE} (a trained model's)", GaussianScene(
            scene.means, scene.quats, scene.scales, scene.opacities, np.concatenate([scene.sh, rest], 1), SH_DEGREE)))
    return [row for label, s in scenes for row in writer_rows(s, folder, warmup, repeats, label)]


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    p.add_argument("--checkpoint", help=f"a trained model, or {SHIPPED.name!r}: the shipped one (default: a fresh "
                   "model of the model flags)")
    add_device_argument(p)
    p.add_argument("--size", type=argtype(parse_size, "--size"), default=(320, 256),
                   help="input pair (video: one eye's frame) size WxH, multiples of 16 (default 320x256)")
    p.add_argument("--warmup", type=whole_number("--warmup", 0), default=3,
                   help="untimed pairs (video: batches) first (default 3)")
    p.add_argument("--repeats", type=whole_number("--repeats"), default=10,
                   help="timed pairs (video: model-alone batches) (default 10)")
    add_precision_argument(p)
    p.add_argument("--video", action="store_true", help="a synthetic side-by-side video instead: pairs/s and "
                   "latency of the model alone and end to end (decode, model, one novel view, encode)")
    p.add_argument("--batch-size", type=whole_number("--batch-size"), default=1,
                   help="video: pairs per model call (default 1)")
    p.add_argument("--frames", type=whole_number("--frames"), default=120,
                   help="video: frames of the synthetic video (default 120)")
    p.add_argument("--scene-formats", nargs="*", choices=list(FORMATS), default=list(FORMATS),
                   help="video: also run end to end with a scene per frame in each of these formats, as "
                   "`predict --video --frames` does (default: every format; none: only without scenes)")
    p.add_argument("--scene-writers", type=whole_number("--scene-writers"), default=SCENE_WRITERS,
                   help=f"video: processes writing those scenes (default as predict: the usable cores but 4, 2 to "
                   f"12; {SCENE_WRITERS} here)")
    p.add_argument("--out", type=Path, help="also write the markdown table here (a report of an earlier run of this "
                   "bench is replaced, any other file refused)")
