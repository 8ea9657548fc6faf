"""The two compiled compositing variants (cooperative shared-memory blocks, used on CUDA, and one thread
per pixel, used on the CPU) are the same computation: both run here on the CPU and must agree exactly,
so the CUDA default is covered by the CPU test suite too."""

from __future__ import annotations

import math

import pytest
import torch

from scenesplat_stereo.raster.binning import bin_gaussians
from scenesplat_stereo.raster.composite import composite_forward
from scenesplat_stereo.raster.projection import project_gaussians


def _scene(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    z = 1.5 + 4.0 * torch.rand(n, generator=g)
    means = torch.stack([(torch.rand(n, generator=g) - 0.5) * z, (torch.rand(n, generator=g) - 0.5) * z, z], -1)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.01), math.log(0.3), generator=g))
    opacities = torch.rand(n, generator=g)
    return means, quats, scales, opacities


@pytest.mark.parametrize("tile_size", [8, 12, 16, 32])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_cooperative_and_per_pixel_agree_exactly(tile_size: int, channels: int) -> None:
    width, height = 45, 37  # not multiples of the tile size
    means, quats, scales, opacities = _scene(1500, seed=channels)
    viewmats = torch.eye(4)[None].repeat(2, 1, 1)
    viewmats[1, 0, 3] = 0.2
    Ks = torch.tensor([[40.0, 0, 22.5], [0, 40.0, 18.5], [0, 0, 1]])[None].repeat(2, 1, 1)
    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, 0.01, 1e10, 0.3, True,
                             tile_size)
    colors = torch.rand(2, 1500, channels, generator=torch.Generator().manual_seed(7))
    bins = bin_gaussians(proj, width, height, tile_size)
    assert bins.flatten_ids.numel() > 0
    args = (proj.means2d, proj.conics, colors, proj.opacities, bins, width, height, tile_size, 0.99, proj.touch_extents)
    per_pixel = composite_forward(*args, cooperative=False)
    cooperative = composite_forward(*args, cooperative=True)
    for a, b in zip(per_pixel, cooperative):
        assert torch.equal(a, b)
    assert float(per_pixel[1].max()) > 0.5  # the scene really covers the image


@pytest.mark.parametrize("tile_size", [8, 12, 16])
def test_backward_reductions_agree(tile_size: int) -> None:
    """The three pixel reductions of the compositing backward (per-pixel atomics: the CPU default; warp
    sums + atomics: the CUDA default; deterministic rows) give the same gradients up to summation order."""
    from scenesplat_stereo.raster.composite_backward import composite_backward

    width, height, channels = 45, 37, 4
    means, quats, scales, opacities = _scene(800, seed=11)
    viewmats = torch.eye(4)[None]
    Ks = torch.tensor([[40.0, 0, 22.5], [0, 40.0, 18.5], [0, 0, 1]])[None]
    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, 0.01, 1e10, 0.3, True,
                             tile_size)
    g = torch.Generator().manual_seed(3)
    colors = torch.rand(1, 800, channels, generator=g)
    bins = bin_gaussians(proj, width, height, tile_size)
    args = (proj.means2d, proj.conics, colors, proj.opacities, bins, width, height, tile_size, 0.99)
    _, alphas, last_ids = composite_forward(*args, proj.touch_extents)
    v_render = torch.randn(1, height, width, channels, generator=g)
    v_alphas = torch.randn(1, height, width, 1, generator=g)
    grads = {r: composite_backward(*args, alphas, last_ids, v_render, v_alphas, reduction=r)
             for r in ("pixel", "warp", "rows")}
    ref = grads["pixel"]
    assert float(ref.abs().sum()) > 0
    for r in ("warp", "rows"):
        torch.testing.assert_close(grads[r], ref, rtol=1e-5, atol=1e-6 * float(ref.abs().max()))
