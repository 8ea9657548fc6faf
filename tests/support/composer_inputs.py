"""Composer inputs for the tests of ``sgmodel.model.composer`` and of its CUDA kernels."""

from __future__ import annotations

import torch


def make_inputs(B=2, H=6, W=24, seed=0, scale=3.0, dtype=torch.float64):
    """Random residuals and depth maps with one vertical step edge each (smooth elsewhere), so that the
    dilated band covers part of the canvas only."""
    g = torch.Generator().manual_seed(seed)
    front = scale * torch.randn(B, 37, H, W, generator=g, dtype=torch.float64)
    back = scale * torch.randn(B, 37, H, W, generator=g, dtype=torch.float64)
    dz = 2.0 * torch.randn(B, 1, H, W, generator=g, dtype=torch.float64)
    u = torch.arange(W, dtype=torch.float64)
    v = torch.arange(H, dtype=torch.float64)[:, None]
    z = torch.empty(B, 1, H, W, dtype=torch.float64)
    z[0, 0] = torch.where(u <= 2, 1.0, 3.0 + 0.01 * u) + 0.005 * v  # step between columns 2 and 3
    z[1, 0] = torch.where(u <= 18, 6.0 - 0.02 * u, 0.5) + 0.01 * v  # step between columns 18 and 19
    rgb = torch.rand(B, 3, H, W, generator=g, dtype=torch.float64)
    K = torch.tensor([[[60.0, 0.0, 11.0], [0.0, 55.0, 3.2], [0.0, 0.0, 1.0]],
                      [[40.0, 0.0, 12.5], [0.0, 44.0, 2.7], [0.0, 0.0, 1.0]]], dtype=torch.float64)[:B]
    baseline = torch.tensor([0.12, 0.3], dtype=torch.float64)[:B]
    return [t.to(dtype) for t in (front, back, dz, z, rgb, K, baseline)]
