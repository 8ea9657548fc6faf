"""A Gaussian scene seen from a rotated camera frame: means, orientations and view-dependent colour.

``rotate_gaussians(g, R)`` returns the scene with every point p expressed as R p: means R m, rotations
R Rot(q) (quaternion q(R) * q, wxyz), scales and opacities unchanged, and each SH band rotated so that the
colour seen along a direction d of the new frame is the colour the old scene showed along R^T d. The SH basis
is the rasteriser's (INRIA / gsplat order and signs: ``scenesplat_stereo.raster.sh.sh_basis``), degrees 0..3.

Band l of the real SH basis is closed under rotation: Y_l(R^T d) = M_l Y_l(d) for a (2l+1) x (2l+1) matrix
M_l. ``sh_rotation`` finds M_l in float64 by least squares on a fixed set of directions (exact up to
rounding, since both sides lie in the same space), and the coefficients become a'_l = M_l^T a_l, so that
sum a'_l Y_l(d) = sum a_l Y_l(R^T d).
"""

from __future__ import annotations

import numpy as np
import torch

from scenesplat_stereo.raster.sh import sh_basis
from scenesplat_stereo.scene.cameras import fibonacci_directions

#: Directions the band matrices are fitted on (more than the 7 unknowns per row of band 3, well spread).
_FIT_DIRECTIONS = 64


def sh_rotation(R: np.ndarray, degree: int) -> np.ndarray:
    """The [(degree+1)^2, (degree+1)^2] float64 matrix A with coefficients' = A coefficients (block-diagonal
    per band, A[0, 0] = 1) for the scene rotated by R [3,3] (new point = R old point)."""
    R = np.asarray(R, dtype=np.float64)
    d = torch.from_numpy(fibonacci_directions(_FIT_DIRECTIONS))
    Y = sh_basis(degree, d).numpy()                                   # [n, K] at d
    Y_old = sh_basis(degree, d @ torch.from_numpy(R)).numpy()         # [n, K] at R^T d (rows d^T R)
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


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of wxyz quaternions [..., 4] (broadcast)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def rotate_gaussians(gaussians: dict[str, torch.Tensor], R: np.ndarray) -> dict[str, torch.Tensor]:
    """The Gaussians dict (means [B,N,3], quats [B,N,4] wxyz, scales, opacities, sh [B,N,K,3]) with every
    point p replaced by R p (R [3,3] a rotation, float64); computed in float64, returned in the input dtypes
    on the input device. Quaternions keep their norm."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) <= 0:
        raise ValueError(f"rotate_gaussians: R must be a 3x3 rotation matrix, got {R.tolist()}")
    means, quats, sh = gaussians["means"], gaussians["quats"], gaussians["sh"]
    k = sh.shape[-2]
    degree = round(k ** 0.5) - 1
    if (degree + 1) ** 2 != k or degree > 3:
        raise ValueError(f"rotate_gaussians: sh must hold (d+1)^2 coefficients, d in 0..3, got {k}")
    Rt = torch.from_numpy(R).to(means.device)
    q = torch.from_numpy(rotation_to_quaternion(R)).to(means.device)
    A = torch.from_numpy(sh_rotation(R, degree)).to(means.device)
    out = dict(gaussians)
    out["means"] = (means.double() @ Rt.T).to(means.dtype)
    out["quats"] = quaternion_multiply(q, quats.double()).to(quats.dtype)
    out["sh"] = torch.einsum("ij,...jc->...ic", A, sh.double()).to(sh.dtype)
    return out
