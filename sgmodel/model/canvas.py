"""The expanded canvas (paper section 4.3 "Expanded field of view", appendix A "Canvas geometry").

After decoding at the original resolution, the reference RGB, the processed depth and the descriptor are
extended by edge replication with P pixels per side, to Hc x Wc = (H + 2P) x (W + 2P). The canvas
intrinsics keep the focal lengths and shift the principal point by P (eq. canvas-intrinsics), so padded
pixels define rays outside the original frustum. Target cameras keep their own K and size. The
descriptor is extended where the predictor concatenates it with the other inputs (``layers.cat_channels``'
``pads``: on CUDA in the same pass, without a padded copy); the RGB and depth here, since the composer
reads them too.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from sgmodel.model.layers import replicate_pad


@dataclass
class Canvas:
    """The predictor's inputs on the canvas: rgb [B,3,Hc,Wc] in [0,1], depth z~ [B,1,Hc,Wc] metres,
    K~ [B,3,3] pixels."""

    rgb: torch.Tensor
    depth: torch.Tensor
    K: torch.Tensor


def canvas_intrinsics(K: torch.Tensor, padding: int) -> torch.Tensor:
    """K~ [..., 3, 3]: cx + P, cy + P; focal lengths unchanged (pixels)."""
    Kc = K.clone()
    Kc[..., 0, 2] = K[..., 0, 2] + padding
    Kc[..., 1, 2] = K[..., 1, 2] + padding
    return Kc


def extend(x: torch.Tensor, padding: int) -> torch.Tensor:
    """[B, C, H, W] -> [B, C, H + 2P, W + 2P] by edge replication (each padded pixel copies the nearest
    border pixel)."""
    return replicate_pad(x, padding)
