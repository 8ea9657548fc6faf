"""A Gaussian scene under a similarity transform p -> k R p + t: means, orientations, sizes and view-dependent
colour, in float64 (numpy).

``transform_scene(scene, R, k, t)`` returns the scene with every point p at k R p + t: means k R m + t,
rotations R Rot(q) (quaternion q(R) * q, wxyz), scales k s (log-scales log s + log k), opacities unchanged,
and each SH band rotated so that the colour seen along a direction d of the new frame is the colour the old
scene showed along R^T d (scaling and moving do not change directions). The SH basis is the scene's
(``scenesplat_stereo.scene.harmonics``: INRIA / gsplat order and signs), degrees 0..3.

Band l of the real SH basis is closed under rotation: Y_l(R^T d) = M_l Y_l(d) for a (2l+1) x (2l+1) matrix
M_l. ``sh_rotation`` finds M_l in float64 by least squares on a fixed set of directions (exact up to
rounding, since both sides lie in the same space), and the coefficients become a'_l = M_l^T a_l, so that
sum a'_l Y_l(d) = sum a_l Y_l(R^T d). ``sgmodel.pairs.rotate`` applies the same matrices to torch tensors.
"""

from __future__ import annotations

import math

import numpy as np

from scenesplat_stereo.scene.cameras import fibonacci_directions
from scenesplat_stereo.scene.gaussians import GaussianScene
from scenesplat_stereo.scene.harmonics import sh_basis

#: Directions the band matrices are fitted on (more than the 7 unknowns per row of band 3, well spread).
_FIT_DIRECTIONS = 64


def check_rotation(R: np.ndarray, where: str) -> np.ndarray:
    """R as a float64 [3, 3] rotation matrix (orthonormal within 1e-9, det > 0); ValueError naming ``where``."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.isfinite(R).all() or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) \
            or np.linalg.det(R) <= 0:
        raise ValueError(f"{where}: R must be a 3x3 rotation matrix, got {R.tolist()}")
    return R


def sh_rotation(R: np.ndarray, degree: int) -> np.ndarray:
    """The [(degree+1)^2, (degree+1)^2] float64 matrix A with coefficients' = A coefficients (block-diagonal
    per band, A[0, 0] = 1) for the scene rotated by R [3,3] (new point = R old point)."""
    R = np.asarray(R, dtype=np.float64)
    d = fibonacci_directions(_FIT_DIRECTIONS)
    Y = sh_basis(degree, d)                                           # [n, K] at d
    Y_old = sh_basis(degree, d @ R)                                   # [n, K] at R^T d (rows d^T R)
    A = np.zeros((Y.shape[1], Y.shape[1]))
    A[0, 0] = 1.0                                                     # band 0 is constant: exactly kept
    for l in range(1, degree + 1):
        band = slice(l * l, (l + 1) * (l + 1))
        A[band, band] = np.linalg.lstsq(Y[:, band], Y_old[:, band], rcond=None)[0]   # Y M^T = Y_old: M^T
    return A


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix R [3,3] (float64)."""
    R = np.asarray(R, dtype=np.float64)
    m = np.array([[R[0, 0] + R[1, 1] + R[2, 2], R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]],
                  [R[2, 1] - R[1, 2], R[0, 0] - R[1, 1] - R[2, 2], R[0, 1] + R[1, 0], R[0, 2] + R[2, 0]],
                  [R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], R[1, 1] - R[0, 0] - R[2, 2], R[1, 2] + R[2, 1]],
                  [R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], R[2, 2] - R[0, 0] - R[1, 1]]]) / 3
    w, v = np.linalg.eigh(m)                                          # the eigenvector of the largest eigenvalue
    q = v[:, np.argmax(w)]
    return q if q[0] >= 0 else -q


def quaternion_left_matrix(q: np.ndarray) -> np.ndarray:
    """The float64 [4, 4] matrix L with L p = q * p (Hamilton product of wxyz quaternions): a rotation's
    quaternion applied to every row p of a table is ``table @ L.T``."""
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def transform_scene(scene: GaussianScene, R: np.ndarray | None = None, scale: float = 1.0,
                    offset: np.ndarray = (0.0, 0.0, 0.0)) -> GaussianScene:
    """The scene with every point p at ``scale`` R p + ``offset`` (R [3, 3] a rotation, ``scale`` > 0, offset in
    the new frame's units; R None: no turn); computed in float64, returned as a float32 ``GaussianScene``.
    ValueError for a bad R, scale or offset."""
    R = check_rotation(np.eye(3) if R is None else R, "transform_scene")
    offset = np.asarray(offset, dtype=np.float64)
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"transform_scene: scale must be a finite number > 0, got {scale!r}")
    if offset.shape != (3,) or not np.isfinite(offset).all():
        raise ValueError(f"transform_scene: offset must be 3 finite numbers, got {offset.tolist()}")
    L = quaternion_left_matrix(rotation_to_quaternion(R))
    A = sh_rotation(R, scene.sh_degree)
    means = scale * (scene.means.astype(np.float64) @ R.T) + offset
    quats = scene.quats.astype(np.float64) @ L.T
    sh = np.einsum("ij,njc->nic", A, scene.sh.astype(np.float64))
    scales = np.exp(np.log(scene.scales.astype(np.float64)) + math.log(scale))
    return GaussianScene(means.astype(np.float32), quats.astype(np.float32), scales.astype(np.float32),
                         scene.opacities.copy(), sh.astype(np.float32), scene.sh_degree)
