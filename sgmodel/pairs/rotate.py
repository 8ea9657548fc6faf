"""The model's Gaussians (torch tensors) seen from a rotated camera frame: ``rotate_gaussians`` applies the
scene transform's float64 matrices (``scenesplat_stereo.scene.transform``: means R m, quaternions q(R) * q, SH
bands rotated) to a batch of tensors on their device.
"""

from __future__ import annotations

import numpy as np
import torch

from scenesplat_stereo.scene.transform import (
    check_rotation,
    quaternion_left_matrix,
    rotation_to_quaternion,
    sh_rotation,
)


def rotate_gaussians(gaussians: dict[str, torch.Tensor], R: np.ndarray) -> dict[str, torch.Tensor]:
    """The Gaussians dict (means [B,N,3], quats [B,N,4] wxyz, scales, opacities, sh [B,N,K,3]) with every
    point p replaced by R p (R [3,3] a rotation, float64); computed in float64, returned in the input dtypes
    on the input device. Quaternions keep their norm; scales and opacities are the input tensors."""
    R = check_rotation(R, "rotate_gaussians")
    means, quats, sh = gaussians["means"], gaussians["quats"], gaussians["sh"]
    k = sh.shape[-2]
    degree = round(k ** 0.5) - 1
    if (degree + 1) ** 2 != k or degree > 3:
        raise ValueError(f"rotate_gaussians: sh must hold (d+1)^2 coefficients, d in 0..3, got {k}")
    Rt = torch.from_numpy(R).to(means.device)
    L = torch.from_numpy(quaternion_left_matrix(rotation_to_quaternion(R))).to(means.device)
    A = torch.from_numpy(sh_rotation(R, degree)).to(means.device)
    out = dict(gaussians)
    out["means"] = (means.double() @ Rt.T).to(means.dtype)
    out["quats"] = (quats.double() @ L.T).to(quats.dtype)
    out["sh"] = torch.einsum("ij,...jc->...ic", A, sh.double()).to(sh.dtype)
    return out
