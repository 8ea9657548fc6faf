"""A synthetic IRS-like scene variant for tests, rendered through ``scenesplat_stereo.raster.rasterization``.

The scene is ``demo.make_room`` (metres, z up) with a per-Gaussian colour speckle added, so that SIFT finds
features the way it does on IRS's photographic textures. The left camera follows a known smooth
trajectory (``synthetic_trajectory``: a sideways sweep across the room looking at the far wall, with some
yaw, pitch and height variation, giving COLMAP enough parallax); the right camera is ``T_L Trans(0.1, 0, 0)``.

Files, as in IRS: ``l_<n>.png`` and ``r_<n>.png`` (8-bit RGB) and ``d_<n>.exr`` (one float32 channel),
n = 1..F. Images are 1/4 of IRS's 960x540 (240x135) by default, with the intrinsics scaled accordingly
(fx = fy = 120, cx, cy = 120, 67.5). The disparity is stored in IRS-native pixels (at 960 px width), i.e.
d = 48 / z with z the rendered expected depth in metres, so the pipeline's z = 48 / d holds unchanged
(a disparity measured at 240 px would be 4x smaller). Pixels the render leaves mostly empty (alpha < 0.5)
get d = 0 (invalid), as holes would in a real disparity map.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.irs import IRS_BASELINE, IRS_CAMERA, IRS_FOCAL_BASELINE
from scenesplat_stereo.captured.colmap import PinholeCamera

SYNTHETIC_SIZE = (240, 135)  # 1/4 of IRS's 960x540
SPECKLE = 0.12  # std of the per-Gaussian colour speckle (SH DC units, about 0.034 in rgb)


@dataclass
class SyntheticVariant:
    """A written variant: its folder, camera, and ground-truth left poses [F,4,4] (c2w OpenCV, metres)
    of frames 1..F."""

    folder: Path
    camera: PinholeCamera
    c2w: np.ndarray

    @property
    def trajectory_length(self) -> float:
        """Sum of the distances between consecutive camera centres, metres."""
        return float(np.linalg.norm(np.diff(self.c2w[:, :3, 3], axis=0), axis=1).sum())


def synthetic_trajectory(n_frames: int) -> np.ndarray:
    """Left c2w poses [F,4,4] (OpenCV, metres) in ``make_room``'s 4 x 5 x 2.6 m room (z up): the eye
    sweeps 2 m sideways (x 1.0 -> 3.0) at y about 1.6 m and 1.2-1.4 m height, looking towards the far wall
    (+y, about 3.4 m away) with +-7 deg of yaw and a slight downward pitch. (Larger yaw swings at this
    image size leave COLMAP's rotation-translation trade-off less well determined.)"""
    from scenesplat_stereo.scene.cameras import look_at

    a = np.linspace(0.0, 1.0, n_frames)
    eyes = np.column_stack([1.0 + 2.0 * a, 1.6 + 0.25 * np.sin(np.pi * a), 1.3 + 0.1 * np.sin(3 * np.pi * a)])
    yaw = 0.12 * np.sin(2 * np.pi * a)
    ahead = np.column_stack([np.sin(yaw), np.cos(yaw), np.full(n_frames, -0.25)])
    return look_at(eyes, eyes + ahead, up=(0.0, 0.0, 1.0))


def _render(scene: dict, sh_degree: int, c2w: np.ndarray, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """RGB [C,H,W,3] in [0,1] and expected depth [C,H,W] (metres, 0 where alpha < 0.5)."""
    import torch

    from scenesplat_stereo.raster import rasterization
    from scenesplat_stereo.scene.cameras import viewmats_from_c2w

    viewmats = torch.tensor(viewmats_from_c2w(c2w), dtype=torch.float32)
    Ks = torch.tensor(np.repeat(camera.K[None], len(c2w), axis=0), dtype=torch.float32)
    colors, alphas, _ = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                      scene["colors"], viewmats, Ks, camera.width, camera.height,
                                      sh_degree=sh_degree, render_mode="RGB+ED", rasterize_mode="antialiased")
    rgb = colors[..., :3].clamp(0, 1).numpy()
    depth = np.where(alphas[..., 0].numpy() >= 0.5, colors[..., 3].numpy(), 0.0)
    return rgb, depth


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(np.ascontiguousarray(np.rint(rgb * 255).astype(np.uint8)))
    if not buf.write(str(path)):
        raise OSError(f"{path}: {buf.geterror()}")


def write_disparity_exr(path: Path, disparity: np.ndarray) -> None:
    """A one-channel float32 EXR of disparity [H,W] (pixels at IRS's native width)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(np.ascontiguousarray(disparity, dtype=np.float32)[:, :, None])
    if not buf.write(str(path), oiio.FLOAT):
        raise OSError(f"{path}: {buf.geterror()}")


def cached_variant(base: Path, n_frames: int = 32) -> SyntheticVariant:
    """The default variant under ``base/irs_synthetic/Home/Synth`` (``base``: e.g. pytest's session temp
    folder), rendered once and reused by every test module (``gt_c2w.npy`` marks it complete)."""
    folder = Path(base) / "irs_synthetic" / "Home" / "Synth"
    marker = folder / "gt_c2w.npy"
    if marker.is_file():
        return SyntheticVariant(folder, IRS_CAMERA.scaled(*SYNTHETIC_SIZE), np.load(marker))
    variant = write_variant(folder, n_frames)
    np.save(folder / ".gt_c2w.npy", variant.c2w)
    (folder / ".gt_c2w.npy").replace(marker)
    return variant


def write_variant(folder: Path, n_frames: int = 32, seed: int = 0, num_gaussians: int = 60_000,
                  size: tuple[int, int] = SYNTHETIC_SIZE, batch: int = 8) -> SyntheticVariant:
    """Render a variant of ``n_frames`` stereo frames into ``folder`` (created) and return it."""
    import torch

    from scenesplat_stereo.build.demo import make_room

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    camera = IRS_CAMERA.scaled(*size)
    room = make_room(seed, sh_degree=0, num_gaussians=num_gaussians)
    scene = room.to_torch("cpu")
    speckle = np.random.default_rng(seed + 1).normal(0.0, SPECKLE, (len(room.means), 1, 1)).astype(np.float32)
    scene["colors"] = scene["colors"] + torch.from_numpy(speckle)
    left = synthetic_trajectory(n_frames)
    right = left.copy()
    right[:, :3, 3] += IRS_BASELINE * left[:, :3, 0]
    for start in range(0, n_frames, batch):
        idx = slice(start, min(start + batch, n_frames))
        rgb_l, depth = _render(scene, room.sh_degree, left[idx], camera)
        rgb_r, _ = _render(scene, room.sh_degree, right[idx], camera)
        for k in range(rgb_l.shape[0]):
            n = start + k + 1
            _write_png(folder / f"l_{n}.png", rgb_l[k])
            _write_png(folder / f"r_{n}.png", rgb_r[k])
            z = depth[k]
            disparity = np.where(z > 0, IRS_FOCAL_BASELINE / np.where(z > 0, z, 1.0), 0.0)
            write_disparity_exr(folder / f"d_{n}.exr", disparity)
    return SyntheticVariant(folder, camera, left)


@dataclass
class Alignment:
    """Recovered poses against the truth after a similarity alignment: ``scale`` (least squares, truth
    units per recovered unit), the largest camera-centre error (truth units) and rotation error (deg)."""

    scale: float
    max_centre_error: float
    max_rotation_error_deg: float


def align(c2w: np.ndarray, c2w_true: np.ndarray, scale: float | None = None) -> Alignment:
    """Align recovered c2w [R,4,4] to the true ones (same order): rotation = the chordal L2 mean of
    R_true_i R_i^T (from the camera orientations, well determined even for near-planar paths), scale = the
    least-squares fit of the centred camera centres unless ``scale`` is given (e.g. 1 for poses already in
    metres), translation = the difference of the centroids."""
    U, _, Vt = np.linalg.svd(sum(t[:3, :3] @ r[:3, :3].T for r, t in zip(c2w, c2w_true)))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    X = (c2w[:, :3, 3] - c2w[:, :3, 3].mean(0)) @ R.T
    Y = c2w_true[:, :3, 3] - c2w_true[:, :3, 3].mean(0)
    fit = float((X * Y).sum() / (X * X).sum())
    s = fit if scale is None else scale
    centre = np.linalg.norm(s * X - Y, axis=1).max()
    rel = np.swapaxes(R @ c2w[:, :3, :3], 1, 2) @ c2w_true[:, :3, :3]
    angles = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return Alignment(fit, float(centre), float(angles.max()))
