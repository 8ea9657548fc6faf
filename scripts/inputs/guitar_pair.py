"""A rectified stereo pair of the real guitar teacher, for ``sgmodel predict`` (tests and the GPU run).

``python scripts/inputs/guitar_pair.py GUITAR.ply OUT`` writes OUT/left.png, OUT/right.png and OUT/K.txt (the
FoundationStereo calibration format: K row-major on line 1, the baseline on line 2). The left camera orbits
the median of the Gaussians at 4 units, 20 degrees up; the right camera is BASELINE units to its right.
The guitar's units are arbitrary (it is about 4.4 units tall), so "metres" here are guitar units.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.scene.cameras import orbit_poses, right_camera
from scenesplat_stereo.scene.scene_files import load_scene
from scenesplat_stereo.shards.encode import encode_png, to_uint8

W, H, FX = 320, 256, 280.0  # pixels
BASELINE = 0.3  # guitar units: about 20 px of disparity at 4 units


def render_pair(ply: Path, out: Path) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
    """Write the pair and its calibration; returns K, and the left view's expected depth and alpha
    ([H, W] each) for checks."""
    scene = load_scene(ply)
    c2w = orbit_poses(scene.median(), 4.0, 1, elevation_deg=20.0)[0]
    K = np.array([[FX, 0, W / 2], [0, FX, H / 2], [0, 0, 1]])
    views = torch.tensor(np.stack([np.linalg.inv(c2w), np.linalg.inv(right_camera(c2w, BASELINE))]),
                         dtype=torch.float32)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    g = scene.to_torch(device)
    img, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], views.to(device),
                                  torch.tensor(K, dtype=torch.float32, device=device).expand(2, 3, 3), W, H,
                                  sh_degree=scene.sh_degree, render_mode="RGB+ED", rasterize_mode="antialiased")
    img, alpha = img.cpu(), alpha.cpu()
    out.mkdir(parents=True, exist_ok=True)
    for name, i in (("left", 0), ("right", 1)):
        atomic_write_bytes(out / f"{name}.png", encode_png(to_uint8(img[i, ..., :3].clamp(0, 1).numpy())))
    atomic_write_bytes(out / "K.txt", (" ".join(f"{v:.6f}" for v in K.flatten()) + f"\n{BASELINE}\n").encode())
    return K, img[0, ..., 3], alpha[0, ..., 0]


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: python scripts/inputs/guitar_pair.py GUITAR.ply OUT")
    render_pair(Path(sys.argv[1]), Path(sys.argv[2]))
