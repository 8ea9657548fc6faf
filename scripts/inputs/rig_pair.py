"""A raw stereo rig's pair of a procedural demo room, with its calibration, and the ground truth behind it.

``python scripts/inputs/rig_pair.py OUT [radtan|equidistant]`` writes OUT/left.png, OUT/right.png (what the two raw
cameras see, lens distortion included), OUT/opencv.yml (one OpenCV FileStorage file as ``stereoCalibrate``'s
results are written), OUT/intrinsics.yml + OUT/extrinsics.yml (the two files of OpenCV's stereo_calib
sample) and OUT/camchain.yaml (Kalibr). tests/sgmodel/pairs/test_rig.py and scripts/figures/calibration_figure.py use it.

The rig: a rectified pair (left camera on ``room_trajectory``, right camera ``BASELINE`` m to its right)
"un-rectified": each raw camera is turned by its own small rotation about its centre (Q0, Q1: a point p in
raw camera i's coordinates is Q_i p in the rectified left camera's axes) and has its own intrinsics and lens
distortion. The raw images are rendered as pinhole images of the raw cameras (padded so that the distorted
field of view fits) and then distorted by remapping: each raw pixel looks up the pinhole pixel whose ray
the forward lens model bends onto it, found by inverting that model here in float64 (Newton; independent of
OpenCV's code). Intrinsics are written in OpenCV's convention (integer pixel centres).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from scenesplat_stereo.build.demo import make_room, room_trajectory
from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.shards.encode import encode_png, to_uint8

W, H = 320, 240  # pixels, both raw cameras
BASELINE = 0.1  # metres
SEED, FRAME, N_FRAMES, N_GAUSSIANS = 0, 6, 12, 60_000
# Per camera: (fx, fy, cx, cy) in OpenCV's convention, a rotation vector (radians) from raw to rectified axes.
INTRINSICS = ((252.0, 250.5, 162.3, 117.6), (240.0, 239.2, 156.8, 122.9))
ROTATIONS = ((0.035, -0.05, 0.02), (-0.02, 0.03, -0.03))
DISTORTION = {"radtan": ((-0.12, 0.06, 0.0012, -0.0008, 0.0), (-0.10, 0.04, -0.0006, 0.0011, 0.0)),
              "equidistant": ((0.03, -0.012, 0.004, -0.001), (0.02, -0.008, 0.002, 0.0))}


def distort(xy: np.ndarray, model: str, D: np.ndarray) -> np.ndarray:
    """Forward lens model on normalised pinhole coordinates xy [..., 2] (x/z, y/z) -> distorted [..., 2].

    radtan (OpenCV k1 k2 p1 p2 k3): x (1 + k1 r^2 + k2 r^4 + k3 r^6) + (2 p1 x y + p2 (r^2 + 2 x^2)), y likewise
    with (p1 (r^2 + 2 y^2) + 2 p2 x y). equidistant (k1..k4): theta = atan r, theta_d = theta (1 + k1 theta^2 +
    k2 theta^4 + k3 theta^6 + k4 theta^8), xy theta_d / r."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    if model == "radtan":
        k1, k2, p1, p2, k3 = D
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        return np.stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                         y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], -1)
    r = np.sqrt(r2)
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1 + D[0] * t2 + D[1] * t2 ** 2 + D[2] * t2 ** 3 + D[3] * t2 ** 4)
    scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-300), 1.0)
    return xy * scale[..., None]


def undistort(xy_d: np.ndarray, model: str, D: np.ndarray, iterations: int = 30) -> np.ndarray:
    """The inverse of ``distort`` by Newton's method with a central-difference Jacobian (float64)."""
    xy = xy_d.copy()
    h = 1e-7
    for _ in range(iterations):
        f = distort(xy, model, D) - xy_d
        jx = (distort(xy + [h, 0], model, D) - distort(xy - [h, 0], model, D)) / (2 * h)
        jy = (distort(xy + [0, h], model, D) - distort(xy - [0, h], model, D)) / (2 * h)
        det = jx[..., 0] * jy[..., 1] - jy[..., 0] * jx[..., 1]
        step = np.stack([(jy[..., 1] * f[..., 0] - jy[..., 0] * f[..., 1]) / det,
                         (-jx[..., 1] * f[..., 0] + jx[..., 0] * f[..., 1]) / det], -1)
        xy = xy - step
    return xy


def camera_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@dataclass
class RawRig:
    """The ground truth. c2w_rect: the rectified left camera (OpenCV c2w, metres); Q0, Q1: raw camera axes in
    the rectified left camera's (p_rect = Q_i p_raw_i); K0, K1 (OpenCV convention), D0, D1 (``model``)."""

    model: str
    c2w_rect: np.ndarray
    Q0: np.ndarray
    Q1: np.ndarray
    K0: np.ndarray
    K1: np.ndarray
    D0: np.ndarray
    D1: np.ndarray

    def c2w(self, i: int) -> np.ndarray:
        """OpenCV c2w of raw camera i (0 left, 1 right)."""
        c2w = self.c2w_rect.copy()
        c2w[:3, :3] = self.c2w_rect[:3, :3] @ (self.Q0 if i == 0 else self.Q1)
        c2w[:3, 3] += i * BASELINE * self.c2w_rect[:3, 0]
        return c2w

    @property
    def R(self) -> np.ndarray:
        """stereoCalibrate's R: p1 = R p0 + T."""
        return self.Q1.T @ self.Q0

    @property
    def T(self) -> np.ndarray:
        """stereoCalibrate's T (metres): the left camera's centre in the right camera's coordinates."""
        return self.Q1.T @ np.array([-BASELINE, 0.0, 0.0])


def make_rig(model: str = "radtan") -> RawRig:
    c2w = room_trajectory(N_FRAMES, seed=SEED)[FRAME]
    Q0, Q1 = (cv2.Rodrigues(np.array(r))[0] for r in ROTATIONS)
    K0, K1 = (camera_matrix(*k) for k in INTRINSICS)
    D0, D1 = (np.array(d) for d in DISTORTION[model])
    return RawRig(model, c2w, Q0, Q1, K0, K1, D0, D1)


def room():
    return make_room(SEED, sh_degree=0, num_gaussians=N_GAUSSIANS)


def render(scene, c2ws: list[np.ndarray], Ks: list[np.ndarray], width: int, height: int):
    """RGB [n,H,W,3] in [0,1] and z-depth [n,H,W] metres (0 where alpha < 0.5) of cameras with OpenCV c2w and
    K in this project's convention (pixel centres at +0.5)."""
    g = scene.to_torch("cpu")
    viewmats = torch.tensor(np.linalg.inv(np.stack(c2ws)), dtype=torch.float32)
    with torch.no_grad():
        img, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], viewmats,
                                      torch.tensor(np.stack(Ks), dtype=torch.float32), width, height,
                                      sh_degree=scene.sh_degree, render_mode="RGB+ED", rasterize_mode="antialiased")
    rgb = img[..., :3].clamp(0, 1).numpy()
    depth = np.where(alpha[..., 0].numpy() > 0.5, img[..., 3].numpy(), 0.0)
    return rgb, depth


def raw_pixels_to_pinhole(K: np.ndarray, D: np.ndarray, model: str) -> np.ndarray:
    """For every raw pixel (OpenCV centres), the pinhole (undistorted) pixel of the same ray [H,W,2]."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    xy_d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], -1)
    xy = undistort(xy_d, model, D)
    return np.stack([K[0, 0] * xy[..., 0] + K[0, 2], K[1, 1] * xy[..., 1] + K[1, 2]], -1)


def raw_images(scene, rig: RawRig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The raw left and right images [H,W,3] uint8 and the raw left camera's pinhole z-depth [H,W] (no
    distortion: the depth of the ray through pinhole pixel (u, v), OpenCV centres)."""
    maps = [raw_pixels_to_pinhole(K, D, rig.model) for K, D in ((rig.K0, rig.D0), (rig.K1, rig.D1))]
    pad = int(math.ceil(max(max(-m.min(), m[..., 0].max() - W, m[..., 1].max() - H) for m in maps))) + 2
    pad = max(pad, 2)
    Ks = []
    for K in (rig.K0, rig.K1):
        Kp = K.copy()
        Kp[:2, 2] += 0.5 + pad                  # OpenCV centres -> +0.5, and the padding
        Ks.append(Kp)
    rgb, depth = render(scene, [rig.c2w(0), rig.c2w(1)], Ks, W + 2 * pad, H + 2 * pad)
    out = []
    for image, m in zip(rgb, maps):
        mx, my = (m[..., 0] + pad).astype(np.float32), (m[..., 1] + pad).astype(np.float32)
        out.append(to_uint8(cv2.remap(np.ascontiguousarray(image, dtype=np.float32), mx, my, cv2.INTER_LINEAR)))
    return out[0], out[1], depth[0, pad:pad + H, pad:pad + W]


def opencv_yaml(rig: RawRig, fields: tuple[str, ...] = ("K1", "D1", "K2", "D2", "R", "T", "imageSize")) -> bytes:
    """OpenCV FileStorage YAML (written by cv2.FileStorage) of the rig's fields; M1/M2 spell K1/K2 too."""
    values = {"K1": rig.K0, "M1": rig.K0, "D1": rig.D0[None], "K2": rig.K1, "M2": rig.K1, "D2": rig.D1[None],
              "R": rig.R, "T": rig.T[:, None], "imageSize": (W, H),
              "distortion_model": "fisheye" if rig.model == "equidistant" else "radtan"}
    fs = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    for name in fields:
        fs.write(name, values[name])
    return fs.releaseAndGetString().encode()


def kalibr_yaml(rig: RawRig) -> bytes:
    """Kalibr camchain.yaml of the rig (cam1.T_cn_cnm1 = [R T; 0 0 0 1])."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rig.R, rig.T
    cams = {}
    for i, (K, D) in enumerate(((rig.K0, rig.D0), (rig.K1, rig.D1))):
        coeffs = D[:4] if rig.model == "radtan" else D
        cams[f"cam{i}"] = {"camera_model": "pinhole", "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                                                                       float(K[1, 2])],
                           "distortion_model": rig.model, "distortion_coeffs": [float(c) for c in coeffs],
                           "resolution": [W, H], "rostopic": f"/cam{i}/image_raw", "cam_overlaps": [1 - i]}
    cams["cam1"] = {"T_cn_cnm1": T.tolist(), **cams["cam1"]}
    return yaml.safe_dump(cams, default_flow_style=None, sort_keys=False).encode()


def write_rig(out: Path, model: str = "radtan", scene=None) -> RawRig:
    """Write the raw pair and its calibration files into ``out``; returns the ground truth."""
    rig = make_rig(model)
    left, right, _ = raw_images(room() if scene is None else scene, rig)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "left.png", encode_png(left))
    atomic_write_bytes(out / "right.png", encode_png(right))
    atomic_write_bytes(out / "opencv.yml", opencv_yaml(rig, ("K1", "D1", "K2", "D2", "R", "T", "imageSize",
                                                             "distortion_model")))
    atomic_write_bytes(out / "intrinsics.yml", opencv_yaml(rig, ("M1", "D1", "M2", "D2")))
    atomic_write_bytes(out / "extrinsics.yml", opencv_yaml(rig, ("R", "T")))
    atomic_write_bytes(out / "camchain.yaml", kalibr_yaml(rig))
    return rig


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        raise SystemExit("usage: python scripts/inputs/rig_pair.py OUT [radtan|equidistant]")
    write_rig(Path(sys.argv[1]), *sys.argv[2:])
