"""torch.autograd glue: one Function per rasteriser stage (projection, SH colours, compositing).

Forward passes call the Warp forward stages; backward passes call the hand-written reverse kernels
(projection_backward, sh_backward, composite_backward). Gradients flow to means, quats, scales, opacities
and colours (SH coefficients or plain colours); cameras (viewmats, Ks) get none. Everything the stages
add in torch (depth channel, background, expected depth) is differentiated by torch.

Reproducibility: the compositing backward sums over pixels with float atomics by default, whose order
(and so the last bits of the gradients) can change from run to run on CUDA. ``deterministic=True`` (a
keyword of ``rasterization``, fixed when the forward pass runs) switches to a fixed-order block reduction
that gives bit-identical gradients (costs: see composite_backward). On CPU the default is already
reproducible (Warp runs CPU kernels as one serial loop), so the keyword only matters on CUDA. The
projection and SH backward passes are atomic-free (one thread per Gaussian walks the cameras in order)
and always reproducible.
"""

from __future__ import annotations

import torch

from scenesplat_stereo.raster.binning import Bins
from scenesplat_stereo.raster.composite import composite_forward
from scenesplat_stereo.raster.composite_backward import composite_backward, unpack_splat_grads
from scenesplat_stereo.raster.projection import Projection, project_gaussians
from scenesplat_stereo.raster.projection_backward import project_gaussians_backward
from scenesplat_stereo.raster.sh import eval_sh_colors
from scenesplat_stereo.raster.sh_backward import eval_sh_colors_backward


class ProjectGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane,
                eps2d, antialiased, tile_size, scenes):
        proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane,
                                 far_plane, eps2d, antialiased, tile_size, scenes)
        ctx.mark_non_differentiable(proj.radii, proj.tile_rects, proj.tiles_touched, proj.touch_extents)
        ctx.save_for_backward(means, quats, scales, opacities, viewmats, Ks, proj.radii)
        ctx.config = (width, height, eps2d, antialiased, scenes)
        return (proj.means2d, proj.conics, proj.depths, proj.opacities, proj.radii, proj.tile_rects,
                proj.tiles_touched, proj.touch_extents)

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, v_opacities, _v_radii, _v_rects, _v_tiles, _v_extents):
        means, quats, scales, opacities, viewmats, Ks, radii = ctx.saved_tensors
        if not any(ctx.needs_input_grad[:4]):
            return (None,) * 14
        width, height, eps2d, antialiased, scenes = ctx.config
        v_means, v_quats, v_scales, v_opac = project_gaussians_backward(
            means, quats, scales, opacities, viewmats, Ks, width, height, eps2d, antialiased, radii,
            v_means2d, v_conics, v_depths, v_opacities, scenes,
        )
        grads = [g if need else None for g, need in zip((v_means, v_quats, v_scales, v_opac), ctx.needs_input_grad)]
        return (*grads, *(None,) * 10)


class SHColors(torch.autograd.Function):
    @staticmethod
    def forward(ctx, degree, means, viewmats, coeffs, radii, scenes):
        ctx.save_for_backward(means, viewmats, coeffs, radii)
        ctx.config = (degree, scenes)
        return eval_sh_colors(degree, means, viewmats, coeffs, radii, scenes)

    @staticmethod
    def backward(ctx, v_colors):
        means, viewmats, coeffs, radii = ctx.saved_tensors
        if not (ctx.needs_input_grad[1] or ctx.needs_input_grad[3]):
            return (None,) * 6
        degree, scenes = ctx.config
        v_means, v_coeffs = eval_sh_colors_backward(degree, means, viewmats, coeffs, radii, v_colors, scenes)
        return (None, v_means if ctx.needs_input_grad[1] else None, None,
                v_coeffs if ctx.needs_input_grad[3] else None, None, None)


class CompositeTiles(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, tile_ranges, flatten_ids, tiles_x, tiles_y, width,
                height, tile_size, max_alpha, touch_extents, deterministic):
        bins = Bins(tile_ranges, flatten_ids, tiles_x, tiles_y)
        render, alphas, last_ids = composite_forward(means2d, conics, colors, opacities, bins, width, height,
                                                     tile_size, max_alpha, touch_extents)
        ctx.mark_non_differentiable(last_ids)
        ctx.save_for_backward(means2d, conics, colors, opacities, tile_ranges, flatten_ids, alphas, last_ids)
        ctx.config = (tiles_x, tiles_y, width, height, tile_size, max_alpha, deterministic)
        return render, alphas, last_ids

    @staticmethod
    def backward(ctx, v_render, v_alphas, _v_last_ids):
        means2d, conics, colors, opacities, tile_ranges, flatten_ids, alphas, last_ids = ctx.saved_tensors
        if not any(ctx.needs_input_grad[:4]):
            return (None,) * 14
        tiles_x, tiles_y, width, height, tile_size, max_alpha, deterministic = ctx.config
        packed = composite_backward(
            means2d, conics, colors, opacities, Bins(tile_ranges, flatten_ids, tiles_x, tiles_y), width,
            height, tile_size, max_alpha, alphas, last_ids, v_render, v_alphas, deterministic,
        )
        v_means2d, v_conics, v_colors, v_opac = unpack_splat_grads(packed)
        grads = [g if need else None
                 for g, need in zip((v_means2d, v_conics, v_colors, v_opac), ctx.needs_input_grad)]
        return (*grads, *(None,) * 10)


def _differentiable(*tensors: torch.Tensor) -> bool:
    """Whether autograd would record a stage on these inputs; when it would not (inference, or no input
    that needs a gradient), the stages run without a Function, whose bookkeeping costs host time."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def project(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
            antialiased, tile_size, scenes: int = 1) -> Projection:
    """Differentiable projection (see projection.project_gaussians; ``scenes`` scenes laid end to end)."""
    args = (means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d, antialiased,
            tile_size, scenes)
    if not _differentiable(means, quats, scales, opacities):
        return project_gaussians(*args)
    return Projection(*ProjectGaussians.apply(*args))


def sh_colors(degree: int, means: torch.Tensor, viewmats: torch.Tensor, coeffs: torch.Tensor, radii: torch.Tensor,
              scenes: int = 1) -> torch.Tensor:
    """Differentiable SH colours (see sh.eval_sh_colors; ``scenes`` scenes laid end to end); gradients flow
    to the means (through the view directions) and the coefficients, not to the cameras."""
    if not _differentiable(means, coeffs):
        return eval_sh_colors(degree, means, viewmats, coeffs, radii, scenes)
    return SHColors.apply(degree, means, viewmats, coeffs, radii, scenes)


def composite(means2d, conics, colors, opacities, bins: Bins, width, height, tile_size, max_alpha, touch_extents,
              deterministic: bool = False):
    """Differentiable compositing (see composite.composite_forward; ``touch_extents``, the projection's, only
    bound the forward's walk and get no gradient): (render, alphas, last_ids); ``deterministic`` selects the
    bit-reproducible backward reduction."""
    if not _differentiable(means2d, conics, colors, opacities):
        return composite_forward(means2d, conics, colors, opacities, bins, width, height, tile_size, max_alpha,
                                 touch_extents)
    return CompositeTiles.apply(means2d, conics, colors, opacities, bins.tile_ranges, bins.flatten_ids,
                                bins.tiles_x, bins.tiles_y, width, height, tile_size, max_alpha, touch_extents,
                                bool(deterministic))
