"""The ceiling of the baselines on an ``import multiview`` folder: naive-GS and forward-splat on the sets'
ground-truth disparity (``disp<L>.png``, as the import recorded it) instead of an encoder's, and naive-GS
rendered back into the left camera itself (its blur alone, no parallax). PSNR / SSIM per target group, over the
full image and the valid masks, at the eval's square crop S.

    python scripts/checks/multiview_oracle.py .devdata/multiview [--resolution 256] [--conventions]

``--conventions`` also checks the camera convention: the global horizontal shift of every view against the left
view (OpenCV phase correlation of the grey images at full size: negative = content moved left, i.e. the camera
moved right); forward-splat (true disparity) into each target with its offset scaled by 0.6 .. 1.4, PSNR over
the pixels it lands on (peaks at 1.0 when the offsets' sign and size are right); and naive-GS rendered back into
the left camera with the principal point moved by -0.5 .. 0.5 px (where its own rendering sits on the grid).

The disparity is brought to S x S as ``sgmodel.data`` brings the images (``SquareCrop.nearest``, times the
horizontal scale); pixels with unknown disparity make no Gaussian and splat nothing, as in ``sgmodel.predict.inference``.
Prints a markdown table (rows: method x group). A diagnostic, not a benchmark: no encoder can do better than the
truth, so a baseline far below these rows is the encoder's fault, one near them the renderer's limit.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.common.text import markdown_table
from scenesplat_stereo.shards.encode import decode_image
from sgmodel.metrics import image as metrics
from sgmodel.data.loader import eval_batches
from sgmodel.data.square_crop import SquareCrop
from sgmodel.model import baselines
from sgmodel.model.geometry import depth_from_disparity
from sgmodel.model.render import render_views


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


SCALES = np.round(np.arange(0.6, 1.4001, 0.1), 2)
SHIFTS = np.round(np.arange(-0.5, 0.5001, 0.25), 2)


def _psnr(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    return metrics.psnr(image.clamp(0, 1)[None], target[None], mask[None]).item()


def conventions(data: Path, size: int) -> str:
    """The convention checks of the module docstring, one line per set and per target."""
    import cv2

    report = json.loads((data / "multiview.json").read_text())
    lines = []
    for row in report["sets"]:
        views = sorted(Path(row["folder"]).glob("im*.*"), key=lambda p: int(p.stem[2:]))
        grey = [cv2.cvtColor(decode_image(p.read_bytes(), p.suffix)[..., :3], cv2.COLOR_RGB2GRAY).astype(np.float32)
                for p in views]
        shifts = [cv2.phaseCorrelate(grey[report["pair"][0]], g)[0][0] for g in grey]
        lines.append(f"{row['set']}: shift against im{report['pair'][0]} (px): "
                     + ", ".join(f"im{k} {v:+.2f}" for k, v in enumerate(shifts)))
    for batch in eval_batches(data, "test", 1, size):
        disparity = true_disparity(report, batch["scenes"][0], size)
        K, left, valid = batch["K"], batch["left"], disparity > 0
        z = depth_from_disparity(disparity.clamp(min=1e-3), K[:, 0, 0], batch["baseline"])
        row = next(r for r in report["sets"] if r["set"] == batch["scenes"][0])
        for t, view in enumerate(row["target_views"]):
            psnrs = []
            for scale in SCALES:
                viewmat = batch["target_viewmats"][:, t:t + 1].clone()
                viewmat[..., 0, 3] *= scale
                image, covered = baselines.forward_splat(left, z, K, viewmat, batch["target_Ks"][:, t:t + 1], size,
                                                         size, valid=valid)
                psnrs.append(_psnr(image[0, 0], batch["targets"][0, t], covered[0, 0] & batch["masks"][0, t]))
            lines.append(f"{row['set']} im{view}: forward-splat PSNR over its landed pixels at offset x "
                         f"{SCALES.tolist()}: " + " ".join(f"{v:.2f}" for v in psnrs)
                         + f" (best x {SCALES[int(np.argmax(psnrs))]:g})")
        gaussians = baselines.naive_gs(left, z, K)
        psnrs = []
        for shift in SHIFTS:
            moved = K.clone()
            moved[:, 0, 2] += float(shift)
            image = render_views(gaussians, torch.eye(4)[None, None], moved[:, None], size, size)[0][0, 0]
            psnrs.append(_psnr(image, left[0], torch.ones_like(valid[0])))
        lines.append(f"{row['set']}: naive-GS into the left camera with cx moved by {SHIFTS.tolist()} px: "
                     + " ".join(f"{v:.2f}" for v in psnrs))
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, help="an `import multiview` folder whose sets have disp<L>.png")
    p.add_argument("--resolution", type=int, default=256, help="S of the square crop (default 256, as eval)")
    p.add_argument("--conventions", action="store_true", help="also the camera-convention checks (docstring)")
    args = p.parse_args()
    print(table(measure(args.data, args.resolution)))
    if args.conventions:
        print(conventions(args.data, args.resolution))


if __name__ == "__main__":
    main()
