"""antimatter15's ``.splat`` (the WebGL viewer's format): reader, numpy.

Written from the format as PlayCanvas' splat-transform 3.7.0 reads it (``readSplat``). No header: the file is
N records of 32 bytes, little-endian,

    float32 x, y, z (world units), float32 scale_x, scale_y, scale_z (linear),
    uint8 r, g, b, a (colour = 0.5 + SH_C0 f_dc, a = opacity, each as round(255 value)),
    uint8 w, x, y, z (quaternion component c stored as c * 128 + 128; read as p / 255 * 2 - 1, normalised).

So f_dc = (p / 255 - 0.5) / SH_C0, opacity = clip(a / 255, 1e-6, 1 - 1e-6) (splat-transform's clamp of the
logit), SH degree 0. A record count that is not whole (size not a multiple of 32) or zero is refused; so are
non-finite positions or scales, scales <= 0 and all-zero quaternions (``decoded_scene``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.gaussians import GaussianScene, decoded_scene

#: Bytes a Gaussian.
RECORD = 32
#: The zeroth-degree SH basis constant (colour = 0.5 + SH_C0 f_dc).
SH_C0 = 0.28209479177387814
_DTYPE = np.dtype([("means", "<f4", 3), ("scales", "<f4", 3), ("rgba", "u1", 4), ("quat", "u1", 4)])


class SplatError(ValueError):
    """A ``.splat`` file that cannot be read; names the file and the field."""


def splat_count(path: str | os.PathLike) -> int:
    """Gaussians in a ``.splat`` (its size / 32); ``SplatError`` when the size is not a positive multiple."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as e:
        raise SplatError(f"{path}: cannot open ({e.strerror or e})") from None
    if size == 0 or size % RECORD:
        raise SplatError(f"{path}: size {size} bytes is not a positive multiple of the {RECORD}-byte "
                         f".splat record (truncated, or not a .splat file)")
    return size // RECORD


def load_splat(path: str | os.PathLike) -> GaussianScene:
    """Read a ``.splat`` into a ``GaussianScene`` (module docstring); ``SplatError`` naming the file and field."""
    path = Path(path)
    n = splat_count(path)
    try:
        rec = np.fromfile(path, _DTYPE, n)
    except OSError as e:
        raise SplatError(f"{path}: cannot read ({e.strerror or e})") from None
    if len(rec) != n:
        raise SplatError(f"{path}: read {len(rec)} of {n} records (the file changed while read)")
    with np.errstate(divide="ignore", invalid="ignore"):
        log_scales = np.log(rec["scales"].astype(np.float64))
    if (rec["scales"] <= 0).any():
        bad = np.flatnonzero((rec["scales"] <= 0).any(1))
        raise SplatError(f"{path}: scales: {len(bad)} Gaussians have a scale <= 0 (the first is Gaussian {bad[0]})")
    sh = ((rec["rgba"][:, :3] / 255.0 - 0.5) / SH_C0)[:, None, :]
    opacities = np.clip(rec["rgba"][:, 3] / 255.0, 1e-6, 1.0 - 1e-6)
    quats = rec["quat"] / 255.0 * 2.0 - 1.0
    return decoded_scene(path, SplatError, rec["means"].astype(np.float64), quats, log_scales, opacities, sh, 0)
