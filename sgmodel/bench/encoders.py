"""``sgmodel bench encoders``: each encoder's time and disparity error — what accuracy costs in time.

On a dataset built with ``scenesplat-stereo build --with-depth`` (the left depth is rendered from the
teacher), for every validation pair at S x S: the encoder's time per pair (median over batches, after a
warm-up batch, synchronised on CUDA) and its disparity error against the true disparity d* = fx B / z
over pixels with a rendered depth: end-point error (mean |d - d*|, pixels), the share of pixels off by
more than 3 px and 5% (KITTI's D1), and the mean relative error of the depth clip(fx B / d, 0.1, 10)
that the model anchors its Gaussians on.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch

from scenesplat_stereo.common.measure import synced_clock
from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import markdown_table
from sgmodel.args import add_device_argument, device_from_flag
from sgmodel.bench import report
from sgmodel.data.loader import make_loader, to_device
from sgmodel.encoders import StereoEncoder
from sgmodel.encoders.flags import build_encoder, encoder_label, parse_encoder_spec
from sgmodel.model.geometry import depth_from_disparity

OWNER = "sgmodel bench encoders"  # recorded beside --out: a later run may replace its own report


def disparity_errors(disparity: torch.Tensor, depth: torch.Tensor, fx: torch.Tensor, baseline: torch.Tensor
                     ) -> tuple[float, float, float, int]:
    """(sum of |d - d*|, count of D1 outliers, sum of |z - z*| / z*, valid pixels) over depth > 0."""
    valid = depth > 0
    scale = (fx * baseline).view(-1, 1, 1, 1)
    truth = scale / depth.clamp_min(1e-6)
    err = (disparity - truth).abs()
    d1 = (err > 3) & (err > 0.05 * truth)
    z = depth_from_disparity(disparity, fx, baseline)
    rel = (z - depth).abs() / depth.clamp_min(1e-6)
    return err[valid].sum().item(), d1[valid].sum().item(), rel[valid].sum().item(), int(valid.sum().item())


def bench_encoder(label: str, encoder: StereoEncoder, loader, device: torch.device) -> dict:
    """Time and disparity errors of one built encoder over the loader's pairs."""
    now = synced_clock(device)
    times, epe, d1, rel, n, pairs = [], 0.0, 0.0, 0.0, 0, 0
    for i, batch in enumerate(loader):
        if "depth" not in batch:
            raise ValueError("the dataset has no left_depth.exr: build it with `scenesplat-stereo build --with-depth`")
        batch = to_device(batch, device)
        t0 = now()
        with torch.no_grad():
            disparity = encoder(batch["left"], batch["right"]).disparity.float()
        times.append((now() - t0) / batch["left"].shape[0])
        e, o, r, k = disparity_errors(disparity, batch["depth"], batch["K"][:, 0, 0], batch["baseline"])
        epe, d1, rel, n, pairs = epe + e, d1 + o, rel + r, n + k, pairs + batch["left"].shape[0]
    if n == 0:
        raise ValueError("no pixel with a rendered depth in the split")
    times = times[1:] or times  # the first batch warms the encoder up
    return {"encoder": label, "ms_per_pair": statistics.median(times) * 1e3, "epe": epe / n, "d1": 100 * d1 / n,
            "depth_rel": 100 * rel / n, "pairs": pairs}


def run(args: argparse.Namespace) -> int:
    out = OwnedFile(args.out, "--out", OWNER)  # before any work
    device = torch.device(device_from_flag(args.device))
    specs = [parse_encoder_spec(text) for text in args.encoders]
    encoders = [build_encoder(spec, device) for spec in specs]  # all of them before any is measured
    rows = []
    for spec, encoder in zip(specs, encoders):
        loader = make_loader(args.data, args.split, args.batch_size, args.resolution, None, 0, 0, 0, 1, train=False)
        rows.append(bench_encoder(encoder_label(spec, specs), encoder, loader, device))
    dev = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    table = markdown_table(["encoder", "ms / pair", "EPE (px)", "D1 (%)", "depth rel. error (%)"],
                           [[r["encoder"], f"{r['ms_per_pair']:.1f}", f"{r['epe']:.2f}", f"{r['d1']:.1f}",
                             f"{r['depth_rel']:.1f}"] for r in rows])
    report(f"Encoders on {args.data} ({args.split} split, {rows[0]['pairs']} pairs at {args.resolution}x"
           f"{args.resolution}, batch {args.batch_size}) on {dev}.\n\n{table}\n", out)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="a dataset built with --with-depth")
    p.add_argument("--split", choices=("train", "val", "test"), default="val", help="split (default val)")
    p.add_argument("--encoders", nargs="+", default=["psmnet-kitti", "sgbm"],
                   metavar="NAME[,weights=PATH][,repo=PATH]",
                   help="encoders to compare, each with its own weights file and code checkout where it needs them, "
                        "e.g. foundation-stereo,weights=FS/model_best_bp2.pth,repo=FS (default: psmnet-kitti sgbm)")
    p.add_argument("--resolution", type=int, default=256, help="S (default 256)")
    p.add_argument("--batch-size", type=int, default=4, help="pairs per batch (default 4)")
    add_device_argument(p)
    p.add_argument("--out", type=Path, help="also write the markdown table here (a report of an earlier run of this "
                   "bench is replaced, any other file refused)")
