"""A StereoNVS-Real-like folder for tests, rendered at known stereo cameras from a demo room.

Truth (metres, OpenCV c2w): the left cameras are frames of ``demo.room_trajectory`` (picked unevenly, so
that some pairs are the nearest of several frames and some of none), the right ones ``T_L Trans(B, 0, 0)``
with B = ``BASELINE``; K has fx != fy because the images are a per-axis resize of the size poses_bounds
states (``POSES_SIZE``, focal ``FOCAL``) to ``IMAGE_SIZE``.

Written in StereoNeRF's layout: ``ROOT/<scene>/images/left/<name>``, ``images/right/<name>`` (the same
names) and ``poses_bounds.npy`` [2N, 17] (rows 0..N-1 left, N..2N-1 right). The poses are COLMAP-like: the
world is moved by a known similarity x_colmap = s R x + t (so they are not metric), and each camera is
written in LLFF's column order (down, right, backwards, centre, [H, W, focal]), straight from the
convention, without scenesplat_stereo.captured.llff.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.build.demo import make_room, room_trajectory
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.scene.cameras import intrinsics_matrix, right_camera, viewmats_from_c2w
from scenesplat_stereo.shards.encode import encode_jpeg, encode_png

BASELINE = 0.12  # metres
POSES_SIZE = (200, 60)  # (W, H) that poses_bounds' focal refers to
FOCAL = 150.0  # pixels at POSES_SIZE
IMAGE_SIZE = (96, 48)  # the image files: fx = 150 * 96 / 200 = 72, fy = 150 * 48 / 60 = 120
TRAJECTORY_FRAMES = 24
PICKED = (0, 1, 2, 5, 9, 10, 11)  # frames of the trajectory kept, unevenly spaced


@dataclass
class FixtureScene:
    """One written scene: folder, image names, true metric left c2w [N, 4, 4], true K, the COLMAP-like
    similarity (scale s, rotation R [3, 3], translation t [3]) and the image format."""

    folder: Path
    names: list[str]
    c2w_left: np.ndarray
    K: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    suffix: str

    def to_colmap(self, c2w: np.ndarray) -> np.ndarray:
        """Metric OpenCV c2w [..., 4, 4] -> the same cameras in the COLMAP-like world."""
        out = np.array(c2w, dtype=np.float64, copy=True)
        out[..., :3, :3] = self.rotation @ out[..., :3, :3]
        out[..., :3, 3] = self.scale * out[..., :3, 3] @ self.rotation.T + self.translation
        return out


def true_K() -> np.ndarray:
    sx, sy = IMAGE_SIZE[0] / POSES_SIZE[0], IMAGE_SIZE[1] / POSES_SIZE[1]
    return intrinsics_matrix(FOCAL * sx, FOCAL * sy, IMAGE_SIZE[0] / 2, IMAGE_SIZE[1] / 2)


def rotation_about(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues: the rotation by ``degrees`` about ``axis``."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def llff_row(c2w: np.ndarray, near: float = 0.5, far: float = 9.0) -> np.ndarray:
    """One poses_bounds row of an OpenCV c2w: columns down (+y), right (+x), backwards (-z), centre,
    [H, W, focal] at POSES_SIZE; then near and far."""
    R, c = c2w[:3, :3], c2w[:3, 3]
    hwf = [POSES_SIZE[1], POSES_SIZE[0], FOCAL]
    m = np.column_stack([R[:, 1], R[:, 0], -R[:, 2], c, hwf])
    return np.concatenate([m.reshape(-1), [near, far]])


def render(room, c2w: np.ndarray, K: np.ndarray) -> np.ndarray:
    """uint8 images [C, H, W, 3] of ``room`` at OpenCV c2w [C, 4, 4] with K, antialiased, black background."""
    g = room.to_torch("cpu")
    viewmats = torch.from_numpy(viewmats_from_c2w(c2w)).float()
    Ks = torch.from_numpy(np.repeat(K[None], len(c2w), axis=0)).float()
    colors, _, _ = rasterization(**g, viewmats=viewmats, Ks=Ks, width=IMAGE_SIZE[0], height=IMAGE_SIZE[1],
                                 sh_degree=room.sh_degree, rasterize_mode="antialiased")
    return (colors.clamp(0, 1) * 255).round().to(torch.uint8).numpy()


def write_scene(root: Path, name: str, seed: int, suffix: str = ".jpg", frames: tuple[int, ...] = PICKED,
                right_noise: dict[int, np.ndarray] | None = None, gaussians: int = 3000) -> FixtureScene:
    """Write one scene; ``right_noise`` {pair: 4x4} right-multiplies that pair's true right camera
    (metric) before it is written, to make pairs that disagree."""
    rng = np.random.default_rng(seed)
    c2w_left = room_trajectory(TRAJECTORY_FRAMES, seed=seed)[list(frames)]
    c2w_right = right_camera(c2w_left, BASELINE)
    for i, m in (right_noise or {}).items():
        c2w_right[i] = c2w_right[i] @ m
    names = [f"{1000 + 7 * k:06d}{suffix}" for k in range(len(frames))]
    world = rotation_about(rng.normal(size=3), rng.uniform(20, 160))
    scene = FixtureScene(Path(root) / name, names, c2w_left, true_K(), float(rng.uniform(2.0, 5.0)), world,
                         rng.normal(size=3) * 3.0, suffix)
    room = make_room(seed, sh_degree=1, num_gaussians=gaussians)
    images = render(room, np.concatenate([c2w_left, c2w_right]), scene.K)
    encode = encode_jpeg if suffix in (".jpg", ".jpeg") else encode_png
    for side, block in (("left", images[: len(frames)]), ("right", images[len(frames):])):
        folder = scene.folder / "images" / side
        folder.mkdir(parents=True, exist_ok=True)
        for file, image in zip(scene.names, block):
            (folder / file).write_bytes(encode(image))
    rows = [llff_row(m) for m in scene.to_colmap(np.concatenate([c2w_left, c2w_right]))]
    np.save(scene.folder / "poses_bounds.npy", np.array(rows, dtype=np.float64))
    return scene
