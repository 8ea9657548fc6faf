"""LLFF's ``poses_bounds.npy`` (Mildenhall et al. 2019; read by NeRF, IBRNet, GeoNeRF and StereoNeRF) as
OpenCV cameras. Pure numpy, float64; the one reader of the format.

The file holds an array [N, 17]. Row i is a 3x5 matrix, row-major (15 values), then the near and far
depth bounds of camera i. Columns 0-2 of the 3x5 are the camera's axes in world coordinates, in LLFF's
order **down, right, backwards**; column 3 is the camera centre; column 4 is ``[H, W, focal]``: the image
height and width in pixels that the focal length (pixels, fx = fy) refers to. The principal point is the
image centre. Units are those of the reconstruction (COLMAP's: not metres).

OpenCV axes are right, down, forward, so the OpenCV c2w has columns (right, down, forward, centre) =
(col 1, col 0, -col 2, col 3): ``R_opencv = R_llff @ LLFF_TO_OPENCV``, a proper rotation (det +1).
Intrinsics for images of another size scale per axis (``cameras.scale_intrinsics``): fx = focal W'/W,
fy = focal H'/H, principal point (W'/2, H'/2), so a resize that changes the aspect ratio keeps fx and fy
apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.cameras import intrinsics_matrix, orthonormalize, rigid_error, scale_intrinsics

#: R_opencv = R_llff @ LLFF_TO_OPENCV: OpenCV (right, down, forward) from LLFF (down, right, backwards).
LLFF_TO_OPENCV = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
ROW_LENGTH = 17  # 15 values of the 3x5 matrix, then near and far
RIGID_TOLERANCE = 1e-3  # max |R^T R - I| of a stored rotation; larger is not a rotation
SHARED_TOLERANCE = 1e-6  # relative: every row's H, W and focal must equal the first row's


class LlffError(ValueError):
    """A ``poses_bounds.npy`` that cannot be read as LLFF cameras; the message names the file and field."""


@dataclass(frozen=True)
class LlffCameras:
    """The cameras of one ``poses_bounds.npy``: ``c2w`` [N, 4, 4] OpenCV in the file's units, ``width`` x
    ``height`` the image size (pixels) that ``focal`` (pixels) refers to, ``bounds`` [N, 2] near and far
    (the file's units)."""

    c2w: np.ndarray
    width: int
    height: int
    focal: float
    bounds: np.ndarray

    def intrinsics(self, image_size: tuple[int, int]) -> np.ndarray:
        """K [3, 3] (pixels) of images of ``image_size`` (W, H): focal scaled per axis, centred."""
        K = intrinsics_matrix(self.focal, self.focal, 0.5 * self.width, 0.5 * self.height)
        return scale_intrinsics(K, (self.width, self.height), tuple(image_size))


def llff_to_opencv(matrices: np.ndarray) -> np.ndarray:
    """LLFF 3x4 (or 3x5) matrices [..., 3, >=4] -> OpenCV c2w [..., 4, 4] (the same camera centres)."""
    m = np.asarray(matrices, dtype=np.float64)
    out = np.broadcast_to(np.eye(4), m.shape[:-2] + (4, 4)).copy()
    out[..., :3, :3] = m[..., :3, :3] @ LLFF_TO_OPENCV
    out[..., :3, 3] = m[..., :3, 3]
    return out


def opencv_to_llff(c2w: np.ndarray) -> np.ndarray:
    """OpenCV c2w [..., 4, 4] -> LLFF 3x4 matrices [..., 3, 4] (``LLFF_TO_OPENCV`` is its own inverse)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return np.concatenate([c2w[..., :3, :3] @ LLFF_TO_OPENCV, c2w[..., :3, 3:4]], axis=-1)


def read_poses_bounds(path: Path) -> LlffCameras:
    """Read and check ``path``: shape [N, 17] (N >= 1), finite, one positive H, W (whole pixels) and focal
    for every row, rigid rotations (``RIGID_TOLERANCE``, then re-orthonormalised). LlffError naming the
    file, row and field otherwise."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise LlffError(f"{path}: not a readable .npy array ({e})") from None
    if data.ndim != 2 or data.shape[0] < 1 or data.shape[1] != ROW_LENGTH or not np.issubdtype(data.dtype, np.number):
        raise LlffError(f"{path}: expected a numeric array [N, {ROW_LENGTH}] (LLFF poses_bounds), got "
                        f"{data.dtype} {data.shape}")
    data = data.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if len(bad):
        raise LlffError(f"{path}: row {bad[0]}: non-finite values")
    mats = data[:, :15].reshape(-1, 3, 5)
    hwf = mats[:, :, 4]
    height, width, focal = hwf[0]
    if not (height >= 1 and width >= 1 and focal > 0) or height != round(height) or width != round(width):
        raise LlffError(f"{path}: row 0: [H, W, focal] = {hwf[0].tolist()}: H and W must be whole pixels >= 1 and "
                        "focal > 0")
    off = np.abs(hwf - hwf[0]) > SHARED_TOLERANCE * np.abs(hwf[0])
    if off.any():
        row = int(np.flatnonzero(off.any(axis=1))[0])
        raise LlffError(f"{path}: row {row}: [H, W, focal] = {hwf[row].tolist()} differs from row 0's "
                        f"{hwf[0].tolist()} (one camera for all frames)")
    c2w = llff_to_opencv(mats)
    err = rigid_error(c2w)
    if (err > RIGID_TOLERANCE).any():
        row = int(np.argmax(err))
        raise LlffError(f"{path}: row {row}: columns 0-2 are not a rotation (orthonormality error {err[row]:.3g})")
    return LlffCameras(orthonormalize(c2w), int(round(width)), int(round(height)), float(focal), data[:, 15:17].copy())
