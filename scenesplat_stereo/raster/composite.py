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

from ._warp import ALPHA_MIN, T_MIN, cpu_blocks, on_device_of, to_wp, vector_type
from .binning import Bins


# Per-splat row of the depth-sorted intersection list: mean2d (2), conic (3), opacity (1), then D colours.
SPLAT_SLOTS = 6


@functools.cache
def composite_kernel(channels: int, tile_size: int):
    """The compositing kernel for ``channels`` colour channels and square tiles of ``tile_size`` pixels:
    one thread block per tile, one thread per pixel; the block loads its list in batches of one splat
    per thread into shared memory and every thread walks the batch from there."""
    vecD = vector_type(channels)
    block = tile_size * tile_size
    row = SPLAT_SLOTS + channels

    @wp.kernel(enable_backward=False, module="unique")
    def composite(
        splats: wp.array2d(dtype=float),
        tile_ranges: wp.array2d(dtype=wp.int32),
        width: int,
        height: int,
        tiles_x: int,
        tiles_per_camera: int,
        max_alpha: float,
        out_render: wp.array(dtype=vecD),
        out_alphas: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
    ):
        tile, lane = wp.tid()
        c = tile / tiles_per_camera
        t = tile - c * tiles_per_camera
        ty = t / tiles_x
        tx = t - ty * tiles_x
        px = tx * tile_size + lane % tile_size
        py = ty * tile_size + lane / tile_size
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        done = int(0)
        if px >= width or py >= height:
            done = 1

        T = float(1.0)
        acc = vecD()
        last = int(-1)
        start = tile_ranges[tile, 0]
        end = tile_ranges[tile, 1]
        b = start
        while b < end:
            # Every thread reaches the cooperative calls; the block stops once all its pixels are done.
            if wp.tile_sum(wp.tile(done))[0] == block:
                break
            batch = wp.tile_load(splats, shape=(block, row), offset=(b, 0), storage="shared")
            if done == 0:
                for j in range(wp.min(block, end - b)):
                    dx = batch[j, 0] - fx
                    dy = batch[j, 1] - fy
                    sigma = 0.5 * (batch[j, 2] * dx * dx + batch[j, 4] * dy * dy) + batch[j, 3] * dx * dy
                    if not (sigma >= 0.0):
                        continue
                    alpha = batch[j, 5] * wp.exp(-sigma)
                    if not (alpha >= ALPHA_MIN):
                        continue
                    alpha = wp.min(max_alpha, alpha)
                    next_T = T * (1.0 - alpha)
                    if next_T <= T_MIN:
                        done = 1
                        break
                    w = alpha * T
                    for k in range(channels):
                        acc[k] = acc[k] + w * batch[j, SPLAT_SLOTS + k]
                    T = next_T
                    last = b + j
            b += block
        if px < width and py < height:
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
    # Depth-sorted rows: one contiguous read per batch instead of an id lookup per splat per pixel.
    per_splat = torch.cat([means2d, conics, opacities[..., None], colors], dim=-1).reshape(C * N, SPLAT_SLOTS + D)
    splats = per_splat.index_select(0, bins.flatten_ids)
    with on_device_of(colors) as device, cpu_blocks(device):
        wp.launch_tiled(
            composite_kernel(D, tile_size),
            dim=[C * tiles_per_camera],
            inputs=[
                to_wp(splats), to_wp(bins.tile_ranges), int(width), int(height), bins.tiles_x,
                tiles_per_camera, float(max_alpha),
            ],
            outputs=[
                to_wp(render, vecD, (C * height * width,)), to_wp(alphas, None, (C * height * width,)),
                to_wp(last_ids, None, (C * height * width,)),
            ],
            block_dim=tile_size * tile_size,
            device=device,
        )
    return render, alphas, last_ids
