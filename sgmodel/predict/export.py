"""What ``sgmodel predict`` writes: the scene (``scenesplat_stereo.scene.scene_files`` formats), a colour-mapped
depth image, novel-view cameras around the left camera and the orbit animation.

All in the left camera frame: OpenCV axes (x right, y down, z forward), metres.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import torch

from scenesplat_stereo.scene.cameras import translation
from scenesplat_stereo.scene.gaussians import GaussianScene, content_sh_degree
from sgmodel.model.render import check_gaussians

#: Frames per second of the orbit animation.
ORBIT_FPS = 12


def to_scene(gaussians: dict, index: int = 0, keep: torch.Tensor | None = None) -> GaussianScene:
    """Scene ``index`` of a Gaussians dict -> ``GaussianScene`` (numpy float32) with the rows where ``keep``
    [N] (bool) is False dropped, and its SH cut to the degree the content has (0 when the higher bands are
    all zero, as for naive-GS; ``gaussians.content_sh_degree``).

    Quaternions are normalised (in float64; the contract allows any non-zero norm); scales are linear metres
    and opacities in [0, 1] as in the dict (the writers store what their format needs). From a GPU, the work and
    the copy run on the current stream, which this waits for (not for the device).
    """
    check_gaussians(gaussians)
    g = {k: v[index].detach() for k, v in gaussians.items()}
    if keep is not None:
        rows = torch.nonzero(keep.to(g["means"].device)).squeeze(1)
        g = {k: v.index_select(0, rows) for k, v in g.items()}
    degree = content_sh_degree(g["sh"])  # where the Gaussians live, before anything is copied
    quats = g["quats"].double()
    quats = quats / quats.norm(dim=-1, keepdim=True)
    fields = [g["means"], quats, g["scales"], g["opacities"].clamp(0, 1), g["sh"][:, :(degree + 1) ** 2]]
    flat = torch.cat([f.float().reshape(-1) for f in fields])  # one copy to the host, field after field
    if flat.is_cuda:  # into page-locked memory: a DMA at the bus's rate, on this thread's stream alone
        host, copied = torch.empty(flat.shape, dtype=flat.dtype, pin_memory=True), torch.cuda.Event(blocking=True)
        host.copy_(flat, non_blocking=True)
        copied.record(torch.cuda.current_stream(flat.device))
        copied.synchronize()  # asleep, not spinning on a core the scene writers need
        flat = host
    flat = flat.numpy()  # (its arrays keep the tensor, and so the page-locked block, alive)
    edges = np.cumsum([0] + [f.numel() for f in fields])
    means, quats, scales, opacities, sh = (flat[a:b].reshape(f.shape) for f, a, b in zip(fields, edges, edges[1:]))
    return GaussianScene(means, quats, scales, opacities, sh, sh_degree=degree)


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


def orbit_camera(angle: float, radius: float, focus: float) -> np.ndarray:
    """The viewmat [4,4] of a camera ``radius`` metres from the left camera centre in its image plane at
    ``angle`` radians (0: to the right, pi/2: below, so increasing angles turn clockwise on screen), looking
    at (0, 0, focus)."""
    return _look_at(np.array([radius * math.cos(angle), radius * math.sin(angle), 0.0]), np.array([0.0, 0.0, focus]))


def orbit_cameras(n: int, radius: float, focus: float) -> np.ndarray:
    """n viewmats [n,4,4] evenly spaced on the circle of ``orbit_camera``, starting to the right."""
    return np.stack([orbit_camera(2 * math.pi * i / n, radius, focus) for i in range(n)])


def offset_camera(offset: np.ndarray) -> np.ndarray:
    """The viewmat [4,4] of the left camera moved by ``offset`` [3] metres (its own axes), not turned."""
    return translation(-np.asarray(offset, dtype=np.float64))


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
