"""What ``sgmodel predict`` writes: the scene ``.ply``, a colour-mapped depth image, novel-view cameras
around the left camera and the orbit animation.

All in the left camera frame: OpenCV axes (x right, y down, z forward), metres.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np
import OpenImageIO as oiio
import torch

from scenesplat_stereo.gaussians import GaussianScene, save_ply

from .render import SH_DEGREE, check_gaussians

#: Frames per second of the orbit animation.
ORBIT_FPS = 12


def to_scene(gaussians: dict, index: int = 0) -> GaussianScene:
    """Scene ``index`` of a Gaussians dict -> ``GaussianScene`` (numpy float32, SH degree 2).

    Quaternions are normalised (the contract allows any non-zero norm); scales are linear metres and
    opacities in [0, 1] as in the dict (``save_ply`` stores their log and logit).
    """
    check_gaussians(gaussians)
    g = {k: v[index].detach().to("cpu", torch.float64) for k, v in gaussians.items()}
    quats = g["quats"] / g["quats"].norm(dim=-1, keepdim=True)
    arrays = [g["means"], quats, g["scales"], g["opacities"].clamp(0, 1), g["sh"]]
    return GaussianScene(*(a.numpy().astype(np.float32) for a in arrays), sh_degree=SH_DEGREE)


def write_ply(gaussians: dict, path: str | Path, index: int = 0) -> Path:
    """Write scene ``index`` as an INRIA-layout ``.ply`` (SH degree 2; ``save_ply`` writes atomically)."""
    return save_ply(to_scene(gaussians, index), path)


def depth_png(z: np.ndarray, near: float | None = None, far: float | None = None) -> np.ndarray:
    """z-depth [H,W] metres -> uint8 RGB [H,W,3], turbo colour map on inverse depth.

    Legend: red = near, through yellow and green, to dark blue = far; near/far default to the 2nd and 98th
    percentiles of z (values outside are clipped). Inverse depth spreads the colours like disparity does.
    """
    z = np.asarray(z, dtype=np.float64)
    near = float(np.percentile(z, 2)) if near is None else near
    far = float(np.percentile(z, 98)) if far is None else far
    far = max(far, near * (1 + 1e-6))
    t = (1.0 / np.clip(z, near, far) - 1.0 / far) / (1.0 / near - 1.0 / far)
    bgr = cv2.applyColorMap(np.rint(t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    return np.ascontiguousarray(bgr[..., ::-1])


def _look_at(centre: np.ndarray, focus: np.ndarray) -> np.ndarray:
    """World(= left camera)-to-camera 4x4 of an OpenCV camera at ``centre`` looking at ``focus`` with the
    left camera's down direction (+y) kept as down."""
    f = (focus - centre) / np.linalg.norm(focus - centre)
    x = np.cross([0.0, 1.0, 0.0], f)
    x /= np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, np.cross(f, x), f], axis=1)
    c2w[:3, 3] = centre
    return np.linalg.inv(c2w)


def novel_view_cameras(radius: float, focus: float) -> dict[str, np.ndarray]:
    """Named viewmats [4,4] (float64) around the left camera, each looking at (0, 0, focus):
    centre, and the camera moved ``radius`` metres left, right, up, down and forward (forward at most
    half-way to the focus). ``sgmodel predict`` uses radius = 0.15 x the median depth, focus = median depth."""
    offsets = {"center": (0, 0, 0), "left": (-radius, 0, 0), "right": (radius, 0, 0), "up": (0, -radius, 0),
               "down": (0, radius, 0), "forward": (0, 0, min(radius, 0.5 * focus))}
    target = np.array([0.0, 0.0, focus])
    return {name: _look_at(np.array(o, dtype=np.float64), target) for name, o in offsets.items()}


def orbit_cameras(n: int, radius: float, focus: float) -> np.ndarray:
    """n viewmats [n,4,4] on a circle of ``radius`` metres around the left camera centre in its image
    plane (z = 0), starting to the right and turning clockwise on screen, each looking at (0, 0, focus)."""
    target = np.array([0.0, 0.0, focus])
    angles = 2 * math.pi * np.arange(n) / n
    return np.stack([_look_at(np.array([radius * math.cos(a), radius * math.sin(a), 0.0]), target)
                     for a in angles])


def write_orbit_gif(frames: np.ndarray, path: str | Path, fps: int = ORBIT_FPS) -> Path:
    """Animated GIF of uint8 frames [n,H,W,3] through OpenImageIO, written to a temporary file beside
    ``path`` and moved into place."""
    path = Path(path)
    n, h, w, _ = frames.shape
    spec = oiio.ImageSpec(w, h, 3, "uint8")
    spec.attribute("FramesPerSecond", oiio.TypeRational, (int(fps), 1))
    spec.attribute("oiio:Movie", 1)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    out = oiio.ImageOutput.create(str(tmp))
    try:
        if out is None or not out.open(str(tmp), [spec] * n):
            raise RuntimeError(f"OpenImageIO cannot write the GIF {path}: {oiio.geterror()}")
        for i in range(n):
            if (i and not out.open(str(tmp), spec, "AppendSubimage")) or not out.write_image(frames[i]):
                raise RuntimeError(f"OpenImageIO cannot write frame {i} of {path}: {out.geterror()}")
        out.close()
        os.replace(tmp, path)
    finally:
        if out is not None:
            out.close()
        tmp.unlink(missing_ok=True)
    return path
