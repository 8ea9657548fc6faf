"""Stereo geometry in the left (reference) camera: depth from disparity and unprojection.

Conventions (SPEC section 1 and 7): OpenCV axes (x right, y down, z forward), metres, K in pixels, pixel
(u, v) centred at (u + 0.5, v + 0.5). Disparity d is in pixels of the image it was measured on, positive
= valid, left image as reference (a point at column u in the left image is at u - d in the right one).
"""

from __future__ import annotations

import math

import torch

#: Depth clip of the model, metres (SPEC section 7 "Depth"; paper section 4).
Z_MIN, Z_MAX = 0.1, 10.0


def _per_batch(like: torch.Tensor):
    """x (a number, or a tensor: scalar or [B]) -> what broadcasts over [B,1,H,W] in ``like``'s dtype: a number
    stays a number (made a tensor on a GPU, it would be copied there with a host synchronisation)."""
    def convert(x):
        if not torch.is_tensor(x):
            return float(x)
        x = x.to(dtype=like.dtype, device=like.device)
        return x.reshape(-1, 1, 1, 1) if x.ndim else x
    return convert


def depth_from_disparity(disparity: torch.Tensor, fx: torch.Tensor | float, baseline: torch.Tensor | float,
                         z_min: float = Z_MIN, z_max: float = Z_MAX, doffs: torch.Tensor | float = 0.0) -> torch.Tensor:
    """z = clip(fx B / (d + doffs), z_min, z_max), metres; d + doffs <= 0 (no match) gives z_max.

    disparity [B,1,H,W] pixels; fx [B] or scalar pixels; baseline [B] or scalar metres; doffs [B] or scalar
    pixels, the principal-point offset between the two cameras (Middlebury's ``doffs``, 0 for rectified
    pairs with equal principal points): the true disparity is d + doffs. Returns [B,1,H,W] metres.
    """
    per_batch = _per_batch(disparity)
    d = disparity + per_batch(doffs)
    valid = d > 0
    z = per_batch(fx) * per_batch(baseline) / torch.where(valid, d, torch.ones_like(d))
    return torch.where(valid, z.clamp(z_min, z_max), torch.full_like(d, z_max))


def disparity_validity(disparity: torch.Tensor, fx: torch.Tensor | float, baseline: torch.Tensor | float,
                       doffs: torch.Tensor | float = 0.0, max_disparity: float = math.inf, z_min: float = Z_MIN,
                       z_max: float = Z_MAX) -> torch.Tensor:
    """Which pixels have a stereo depth the model keeps: [B,1,H,W] bool, True where the disparity d is finite,
    d > 0 (an encoder marks "no match" and occlusions with d <= 0), d < ``max_disparity`` (the encoder's
    range: a match at its end may lie further), and the unclipped depth fx B / (d + doffs) lies in
    [z_min, z_max] (so d + doffs > 0). Elsewhere ``depth_from_disparity`` gives a clamp (z_max or z_min),
    not a depth. Arguments as in ``depth_from_disparity``."""
    per_batch = _per_batch(disparity)
    d = disparity + per_batch(doffs)
    fb = per_batch(fx) * per_batch(baseline)
    # z_min <= fx B / d <= z_max with d > 0, written without a division: fx B / z_max <= d <= fx B / z_min
    return (torch.isfinite(disparity) & (disparity > 0) & (disparity < max_disparity) & (d > 0)
            & (d * z_max >= fb) & (d * z_min <= fb))


def pixel_rays(K: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """K^-1 [u + 0.5, v + 0.5, 1]^T for every pixel: [B,3,H,W] rays with z = 1 (K [B,3,3] pixels)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=K.dtype, device=K.device) + 0.5,
                          torch.arange(width, dtype=K.dtype, device=K.device) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1)              # [3, HW]
    return (inverse_intrinsics(K) @ pix).reshape(K.shape[0], 3, height, width)


def inverse_intrinsics(K: torch.Tensor) -> torch.Tensor:
    """K^-1 [B,3,3] of intrinsics K [B,3,3] (``network.check_inputs``: positive focal lengths, last row 0 0 1, so
    det K = fx fy > 0), without the host synchronisation of ``torch.linalg.inv``'s check for singular matrices."""
    return torch.linalg.inv_ex(K).inverse


def unproject(z: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Points z K^-1 [u + 0.5, v + 0.5, 1]^T of a z-depth map z [B,1,H,W] (metres): [B,3,H,W] metres."""
    return z * pixel_rays(K, z.shape[-2], z.shape[-1])
