"""Front-to-back alpha compositing of the binned Gaussians (SPEC section 2, steps 6-8).

One thread per pixel; the threads of a tile are consecutive, so a warp walks one tile's list in lock
step and its loads of a Gaussian are broadcasts. Compiled per channel count D (RGB: 3, RGB+D: 4, D: 1,
plain colours: any D): depth is just one more channel, so a render without depth does no depth work.
Outputs are the raw sums (no background): render = sum alpha_i T_i c_i, alpha = 1 - T, and the index
(into ``flatten_ids``) of the last composited Gaussian per pixel, -1 where none, for the backward pass.
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from ._warp import ALPHA_MIN, T_MIN, on_device_of, to_wp, vector_type
from .binning import Bins


@functools.cache
def composite_kernel(channels: int):
    """The compositing kernel for ``channels`` colour channels."""
    vecD = vector_type(channels)

    @wp.kernel(enable_backward=False, module="unique")
    def composite(
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        colors: wp.array(dtype=vecD),
        opacities: wp.array(dtype=float),
        tile_ranges: wp.array2d(dtype=wp.int32),
        flatten_ids: wp.array(dtype=wp.int32),
        width: int,
        height: int,
        tile_size: int,
        tiles_x: int,
        tiles_per_camera: int,
        max_alpha: float,
        out_render: wp.array(dtype=vecD),
        out_alphas: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
    ):
        tid = wp.tid()
        tile_area = tile_size * tile_size
        tile = tid / tile_area  # camera * tiles_per_camera + tile index
        local = tid - tile * tile_area
        c = tile / tiles_per_camera
        t = tile - c * tiles_per_camera
        ty = t / tiles_x
        tx = t - ty * tiles_x
        px = tx * tile_size + local % tile_size
        py = ty * tile_size + local / tile_size
        if px >= width or py >= height:
            return
        fx = float(px) + 0.5
        fy = float(py) + 0.5

        T = float(1.0)
        acc = vecD()
        last = int(-1)
        for i in range(tile_ranges[tile, 0], tile_ranges[tile, 1]):
            gid = flatten_ids[i]
            m = means2d[gid]
            con = conics[gid]
            dx = m[0] - fx
            dy = m[1] - fy
            sigma = 0.5 * (con[0] * dx * dx + con[2] * dy * dy) + con[1] * dx * dy
            if not (sigma >= 0.0):
                continue
            alpha = opacities[gid] * wp.exp(-sigma)
            if not (alpha >= ALPHA_MIN):
                continue
            alpha = wp.min(max_alpha, alpha)
            next_T = T * (1.0 - alpha)
            if next_T <= T_MIN:
                break
            acc = acc + (alpha * T) * colors[gid]
            T = next_T
            last = i
        pix = (c * height + py) * width + px
        out_render[pix] = acc
        out_alphas[pix] = 1.0 - T
        out_last[pix] = last

    return composite


def composite_forward(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    bins: Bins,
    width: int,
    height: int,
    tile_size: int,
    max_alpha: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite [C, N] screen-space Gaussians with colours [C, N, D] into (render [C,H,W,D] without
    background, alphas [C,H,W,1], last_ids [C,H,W] int32)."""
    C, N, D = colors.shape
    dev = colors.device
    render = torch.zeros(C, height, width, D, device=dev, dtype=torch.float32)
    alphas = torch.zeros(C, height, width, 1, device=dev, dtype=torch.float32)
    last_ids = torch.full((C, height, width), -1, device=dev, dtype=torch.int32)
    if C == 0 or N == 0 or bins.flatten_ids.numel() == 0 or width * height == 0:
        return render, alphas, last_ids
    vecD = vector_type(D)
    tiles_per_camera = bins.tiles_x * bins.tiles_y
    with on_device_of(colors) as device:
        wp.launch(
            composite_kernel(D),
            dim=C * tiles_per_camera * tile_size * tile_size,
            inputs=[
                to_wp(means2d, wp.vec2, (C * N,)), to_wp(conics, wp.vec3, (C * N,)),
                to_wp(colors, vecD, (C * N,)), to_wp(opacities, None, (C * N,)),
                to_wp(bins.tile_ranges), to_wp(bins.flatten_ids), int(width), int(height),
                int(tile_size), bins.tiles_x, tiles_per_camera, float(max_alpha),
            ],
            outputs=[
                to_wp(render, vecD, (C * height * width,)), to_wp(alphas, None, (C * height * width,)),
                to_wp(last_ids, None, (C * height * width,)),
            ],
            device=device,
        )
    return render, alphas, last_ids
