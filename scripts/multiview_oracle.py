"""The ceiling of the baselines on an ``import multiview`` folder: naive-GS and forward-splat on the sets'
ground-truth disparity (``disp<L>.png``, as the import recorded it) instead of an encoder's, and naive-GS
rendered back into the left camera itself (its blur alone, no parallax). PSNR / SSIM per target group, over the
full image and the valid masks, at the eval's square crop S.

    python scripts/multiview_oracle.py .devdata/multiview [--resolution 256]

The disparity is brought to S x S as ``sgmodel.data`` brings the images (``SquareCrop.nearest``, times the
horizontal scale); pixels with unknown disparity make no Gaussian and splat nothing, as in ``sgmodel.inference``.
Prints a markdown table (rows: method x group). A diagnostic, not a benchmark: no encoder can do better than the
truth, so a baseline far below these rows is the encoder's fault, one near them the renderer's limit.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.encode import decode_image
from scenesplat_stereo.text import markdown_table
from sgmodel import baselines, metrics
from sgmodel.data import eval_batches
from sgmodel.geometry import depth_from_disparity
from sgmodel.render import render_views
from sgmodel.square_crop import SquareCrop


def true_disparity(report: dict, scene: str, size: int) -> torch.Tensor:
    """The set's ground-truth disparity [1,1,S,S] in pixels of the S x S crop (0 = unknown)."""
    row = next(r for r in report["sets"] if r["set"] == scene)
    if not row["disparity"]:
        raise SystemExit(f"{scene}: imported without a disparity file; nothing to measure")
    raw = decode_image(Path(row["disparity"]).read_bytes(), ".png")[..., 0].astype(np.float32)
    raw /= report["disparity_scale"]
    crop = SquareCrop.plan(raw.shape[1], raw.shape[0], size)
    return torch.from_numpy(crop.nearest(raw) * (crop.scaled_width / raw.shape[1]))[None, None]


def measure(data: Path, size: int) -> list[dict]:
    """One row per (method, target): method, group, psnr, ssim, psnr_masked."""
    report = json.loads((data / "multiview.json").read_text())
    rows = []
    for batch in eval_batches(data, "test", 1, size):
        disparity = true_disparity(report, batch["scenes"][0], size)
        valid = disparity > 0
        K, left = batch["K"], batch["left"]
        z = depth_from_disparity(disparity.clamp(min=1e-3), K[:, 0, 0], batch["baseline"])
        gaussians = baselines.naive_gs(left, z, K)
        gaussians["opacities"] = gaussians["opacities"] * valid.flatten(1).float()
        views, Ks = batch["target_viewmats"], batch["target_Ks"]
        renders = {"naive-GS (true disparity)": render_views(gaussians, views, Ks, size, size)[0][0],
                   "forward-splat (true disparity)": baselines.forward_splat(left, z, K, views, Ks, size, size,
                                                                             valid=valid)[0][0]}
        targets, masks = batch["targets"][0], batch["masks"][0]
        for name, image in renders.items():
            image = image.clamp(0, 1)
            values = zip(metrics.psnr(image, targets), metrics.ssim(image, targets),
                         metrics.psnr(image, targets, masks))
            for group, (p, s, pm) in zip(batch["target_groups"][0], values):
                rows.append({"method": name, "group": group, "psnr": p.item(), "ssim": s.item(),
                             "psnr_masked": pm.item()})
        itself = render_views(gaussians, torch.eye(4)[None, None], K[:, None], size, size)[0][0].clamp(0, 1)
        rows.append({"method": "naive-GS into the left view itself", "group": "left", "psnr":
                     metrics.psnr(itself, left).item(), "ssim": metrics.ssim(itself, left).item(),
                     "psnr_masked": float("nan")})
    return rows


def table(rows: list[dict]) -> str:
    body = []
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method]
        groups = {r["group"] for r in mine}
        for group in ["left"] if groups == {"left"} else ["all"] + sorted(groups):
            sel = [r for r in mine if group in ("all", r["group"])]
            mean = {k: np.mean(v) if (v := [r[k] for r in sel if not np.isnan(r[k])]) else float("nan")
                    for k in ("psnr", "ssim", "psnr_masked")}
            body.append([method, group, len(sel), f"{mean['psnr']:.2f}", f"{mean['ssim']:.4f}",
                         "n/a" if np.isnan(mean["psnr_masked"]) else f"{mean['psnr_masked']:.2f}"])
    return markdown_table(["method", "targets", "n", "PSNR", "SSIM", "PSNR (valid)"], body)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, help="an `import multiview` folder whose sets have disp<L>.png")
    p.add_argument("--resolution", type=int, default=256, help="S of the square crop (default 256, as eval)")
    args = p.parse_args()
    print(table(measure(args.data, args.resolution)))


if __name__ == "__main__":
    main()
