"""Regenerate ``tests/data/stereo_room_*``: a small rectified stereo pair of a procedural demo room.

Run from the repository root: ``python tests/data/make_stereo_pair.py``. Writes ``stereo_room_left.png``,
``stereo_room_right.png`` (8-bit RGB, what the rasteriser returns clipped to [0, 1]),
``stereo_room_depth_mm.png`` (the left camera's z-depth, 16-bit millimetres, 0 = uncovered) and
``stereo_room.json``: K of both cameras (pixels, OpenCV, pixel centres at +0.5), the baseline in metres
(right camera = left camera moved +B along its own x axis), the left camera's z-depth
percentiles and the true disparity percentiles (fx B / z, pixels) over pixels the scene covers.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from scenesplat_stereo.build.demo import make_room, room_trajectory
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.shards.webdataset import atomic_write_bytes

WIDTH, HEIGHT = 128, 96
FOV_X_DEG = 70.0
BASELINE = 0.1  # metres
SEED, FRAME, N_FRAMES = 0, 3, 12
OUT = Path(__file__).resolve().parent


def render_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(left [H,W,3], right [H,W,3] in [0,1], left z-depth [H,W] metres (0 = uncovered), K [3,3])."""
    scene = make_room(SEED, sh_degree=0, num_gaussians=36_000)
    c2w_left = room_trajectory(N_FRAMES, seed=SEED)[FRAME]
    c2w_right = c2w_left.copy()
    c2w_right[:3, 3] += BASELINE * c2w_left[:3, 0]
    fx = 0.5 * WIDTH / math.tan(math.radians(FOV_X_DEG) / 2)
    K = np.array([[fx, 0, WIDTH / 2], [0, fx, HEIGHT / 2], [0, 0, 1]])
    g = scene.to_torch("cpu")
    viewmats = torch.tensor(np.linalg.inv(np.stack([c2w_left, c2w_right])), dtype=torch.float32)
    Ks = torch.tensor(np.stack([K, K]), dtype=torch.float32)
    with torch.no_grad():
        img, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], viewmats,
                                      Ks, WIDTH, HEIGHT, sh_degree=0, render_mode="RGB+ED",
                                      rasterize_mode="antialiased")
    rgb = img[..., :3].clamp(0, 1).numpy()
    depth = np.where(alpha[0, ..., 0].numpy() > 0.5, img[0, ..., 3].numpy(), 0.0)
    return rgb[0], rgb[1], depth, K


def _png(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor((rgb * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes()


def main() -> None:
    left, right, depth, K = render_pair()
    z = depth[depth > 0]
    q = [5, 50, 95]
    meta = {
        "width": WIDTH, "height": HEIGHT, "K": K.tolist(), "baseline": BASELINE,
        "seed": SEED, "frame": FRAME, "fov_x_deg": FOV_X_DEG,
        "covered_fraction": float(z.size / depth.size),
        "depth_percentiles_m": dict(zip(map(str, q), np.percentile(z, q).round(4).tolist())),
        "disparity_percentiles_px": dict(zip(map(str, q), np.percentile(K[0, 0] * BASELINE / z, q).round(4).tolist())),
    }
    atomic_write_bytes(OUT / "stereo_room_left.png", _png(left))
    atomic_write_bytes(OUT / "stereo_room_right.png", _png(right))
    ok, buf = cv2.imencode(".png", np.round(depth * 1000).astype(np.uint16))
    assert ok
    atomic_write_bytes(OUT / "stereo_room_depth_mm.png", buf.tobytes())
    atomic_write_bytes(OUT / "stereo_room.json", (json.dumps(meta, indent=2) + "\n").encode())
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    main()
