"""torch.autograd glue: one Function per rasteriser stage (projection, SH colours, compositing).

Forward passes call the Warp forward stages. (Backward methods are being added by the backward-pass
work; until then these Functions are forward-only.)
"""

from __future__ import annotations

import torch

from .binning import Bins
from .composite import composite_forward
from .projection import Projection, project_gaussians
from .sh import eval_sh_colors


class ProjectGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane,
                eps2d, antialiased, tile_size):
        proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane,
                                 far_plane, eps2d, antialiased, tile_size)
        ctx.mark_non_differentiable(proj.radii, proj.tile_rects, proj.tiles_touched)
        return (proj.means2d, proj.conics, proj.depths, proj.opacities, proj.radii, proj.tile_rects,
                proj.tiles_touched)


class SHColors(torch.autograd.Function):
    @staticmethod
    def forward(ctx, degree, dirs, coeffs, radii):
        return eval_sh_colors(degree, dirs, coeffs, radii)


class CompositeTiles(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, tile_ranges, flatten_ids, tiles_x, tiles_y, width,
                height, tile_size, max_alpha):
        bins = Bins(tile_ranges, flatten_ids, tiles_x, tiles_y)
        render, alphas, last_ids = composite_forward(means2d, conics, colors, opacities, bins, width, height,
                                                     tile_size, max_alpha)
        ctx.mark_non_differentiable(last_ids)
        return render, alphas, last_ids


def project(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
            antialiased, tile_size) -> Projection:
    """Differentiable projection (see projection.project_gaussians)."""
    out = ProjectGaussians.apply(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane,
                                 far_plane, eps2d, antialiased, tile_size)
    return Projection(*out)


def sh_colors(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """Differentiable SH colours (see sh.eval_sh_colors)."""
    return SHColors.apply(degree, dirs, coeffs, radii)


def composite(means2d, conics, colors, opacities, bins: Bins, width, height, tile_size, max_alpha):
    """Differentiable compositing (see composite.composite_forward): (render, alphas, last_ids)."""
    return CompositeTiles.apply(means2d, conics, colors, opacities, bins.tile_ranges, bins.flatten_ids,
                                bins.tiles_x, bins.tiles_y, width, height, tile_size, max_alpha)
