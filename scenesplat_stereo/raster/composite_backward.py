"""Reverse of the front-to-back compositing (SPEC section 2, steps 6-8): per-pixel gradients to splats.

With T_k the transmittance in front of splat k, alpha_k its alpha, c_k its colour (all D channels, depth
included) and S_k = sum_{j>k} alpha_j T_j c_j the colour composited behind it, a pixel's outputs are
render = sum_k alpha_k T_k c_k and alpha = 1 - T_final, so

    d render / d c_k = alpha_k T_k,
    d render / d alpha_k = T_k c_k - S_k / (1 - alpha_k),      d alpha / d alpha_k = T_final / (1 - alpha_k).

Each pixel walks its tile's list backwards from the last composited splat (``last_ids``) to the tile's
start, recovering T_k = T_{k+1} / (1 - alpha_k) from T_final = 1 - alpha and accumulating S_k as it goes.
Through alpha = o exp(-sigma), sigma = 0.5 delta^T conic delta, delta = mean2d - pixel centre:
d alpha / d o = exp(-sigma), d alpha / d sigma = -alpha. Where the max_alpha clamp binds, alpha is constant
(no gradient to o, conic, mean2d); splats skipped by the 1/255 or sigma >= 0 tests and the splat that
triggered the T <= 1e-4 stop were not composited and get nothing. The same float32 expressions as the
forward kernel decide which splats were composited, so the walk retraces the forward exactly.

Gradients come out packed per (camera, Gaussian) as F = 6 + D floats:
(d mean2d [2] pixels, d conic [3], d o [1], d colour [D]), see ``unpack_splat_grads``.

Three reductions over pixels (``reduction``), one source for CPU and CUDA:
- "pixel" (default on the CPU): one thread per pixel, ``wp.atomic_add`` into the packed gradients. Warp's
  CPU launches are one serial loop, so there this is contention-free and bit-reproducible;
- "warp" (default on CUDA): blocks of one warp (``lanes.LANES`` pixels of a tile) walk the list in lock
  step from the warp's largest ``last_ids``, batches of 32 splats gathered through their ids into shared
  memory (``composite.splat_batch_func``, no depth-sorted rows written first). A tile's list holds every
  splat that reaches the tile, most of which miss a given warp's rows of it: per batch, each lane bounds
  one entry's ellipse against the warp's pixels (``composite.may_touch``, conservative) and one vote
  (``lanes.lanes_ballot``) leaves the entries the walk visits (``lanes.highest_bit``); an entry ruled out
  touches none of the warp's pixels, so skipping it changes no T, S or gradient. Of the entries
  visited, one more warp vote skips those that none of the warp's pixels composited, and one that some
  pixel did is summed over the warp with register shuffles (a reduce-scatter, ``lanes.lanes_sum_add``)
  and added with one atomic instruction per warp (lane 2k adds component k) instead of one per pixel (float atomics add in
  a run-dependent order, so the last bits of the gradients can change between runs). No shared-memory
  reduction or block barrier per entry (the CPU runs the same kernel on fibers through Warp's tile sums);
- "rows" (``deterministic=True``): one block per tile (or per group of at most ``DETERMINISTIC_BLOCK`` pixels of a tile)
  walks the list in lock step; every entry's gradient is summed over the block's pixels with a
  cooperative block reduction (fixed order) and written, without atomics, to that entry's own row; rows
  are then summed per Gaussian in ascending entry order. Bit-reproducible; costs M x F x 4 bytes of rows
  (M = number of tile intersections, times ceil(tile_size^2 / 256)), a block-wide reduction per list
  entry and one stable sort of M ids. On CPU the same kernel runs on Warp's cooperative fibers
  (``wp.config.enable_cpu_blocks``, switched on for the launch only), about 20x slower than the atomic
  path there (20k Gaussians, 320x180: 5.4 s against 0.26-0.5 s on the 2-core test machine), and is
  useful there only to test the CUDA code path.
"""

# No ``from __future__ import annotations`` here: Warp evaluates kernel annotations, and those naming the
# per-D vector types of the kernel factory must be real objects, not strings.
import functools

import torch
import warp as wp

from scenesplat_stereo.raster._warp import ALPHA_MIN, launch, to_wp, vector_type
from scenesplat_stereo.raster.binning import Bins
from scenesplat_stereo.raster.composite import (COMPOSITE_OPTIONS, SPLAT_SLOTS, conic_sigma, gather_splats, lanes_box,
                                                may_touch, splat_batch_func, tile_pixel)
from scenesplat_stereo.raster.lanes import LANES, highest_bit, lanes_any, lanes_ballot, lanes_max, lanes_sum_add

# Pixels per cooperative block in the deterministic reduction (a 16 x 16 tile is one block; larger
# tiles are split into groups of this many pixels, each with its own row per list entry).
DETERMINISTIC_BLOCK = 256
# Leading packed slots before the D colour channels: d mean2d (2), d conic (3), d opacity (1).
SPLAT_GRAD_SLOTS = 6


@wp.func
def walk_pixel(tile: int, local: int, tile_size: int, tiles_x: int, tiles_per_camera: int, width: int, height: int,
               last_ids: wp.array(dtype=wp.int32)):
    """The pixel that lane ``local`` of a cooperative walk over ``tile`` takes: (flat pixel index, its last
    composited list entry, pixel centre x, y). A lane off the image or the tile gets pixel 0 and last entry
    -1, so that it takes part in the lanes' reductions without contributing."""
    c, px, py = tile_pixel(tile, local, tile_size, tiles_x, tiles_per_camera)
    last = int(-1)
    pix = int(0)
    if local < tile_size * tile_size and px < width and py < height:
        pix = (c * height + py) * width + px
        last = last_ids[pix]
    return pix, last, float(px) + 0.5, float(py) + 0.5


@functools.cache
def _kernels(channels: int):
    """(per-pixel atomic kernel, deterministic block kernel factory (group size), warp kernel, row-gather kernel)
    for D channels."""
    vecD = vector_type(channels)
    vecF = vector_type(channels + SPLAT_GRAD_SLOTS)

    @wp.func
    def array_row(splats: wp.array2d(dtype=float), i: int):
        """Row i of the depth-sorted splats: (mean2d, conic, opacity, colour)."""
        col = vecD()
        for k in range(channels):
            col[k] = splats[i, SPLAT_SLOTS + k]
        return (wp.vec2(splats[i, 0], splats[i, 1]), wp.vec3(splats[i, 2], splats[i, 3], splats[i, 4]),
                splats[i, 5], col)

    @wp.func
    def reverse_step(
        m: wp.vec2,
        con: wp.vec3,
        o: float,
        col: vecD,
        fx: float,
        fy: float,
        max_alpha: float,
        T: float,
        T_final: float,
        S: vecD,
        v_rgb: vecD,
        v_alpha: float,
    ):
        """Undo one list entry (mean2d m, conic, opacity o, colour) at pixel centre (fx, fy): (T in front of
        it, S updated, its gradient, 1 if it was composited at this pixel else 0)."""
        grad = vecF()
        dx = m[0] - fx
        dy = m[1] - fy
        sigma = conic_sigma(dx, dy, con[0], con[1], con[2])
        if not (sigma >= 0.0):
            return T, S, grad, 0
        vis = o * wp.exp(-sigma)
        if not (vis >= ALPHA_MIN):
            return T, S, grad, 0
        alpha = wp.min(max_alpha, vis)
        ra = 1.0 / (1.0 - alpha)
        T = T * ra
        fac = alpha * T
        v_a = wp.dot(col * T - S * ra, v_rgb) + v_alpha * T_final * ra
        S = S + fac * col
        for k in range(channels):
            grad[SPLAT_GRAD_SLOTS + k] = fac * v_rgb[k]
        if vis < max_alpha:
            v_sigma = -v_a * vis
            grad[0] = v_sigma * (con[0] * dx + con[1] * dy)
            grad[1] = v_sigma * (con[1] * dx + con[2] * dy)
            grad[2] = v_sigma * 0.5 * dx * dx
            grad[3] = v_sigma * dx * dy
            grad[4] = v_sigma * 0.5 * dy * dy
            grad[5] = v_a * wp.exp(-sigma)
        return T, S, grad, 1

    @wp.kernel(enable_backward=False, module="unique", module_options=COMPOSITE_OPTIONS)
    def composite_backward_atomic(
        splats: wp.array2d(dtype=float),
        tile_ranges: wp.array2d(dtype=wp.int32),
        flatten_ids: wp.array(dtype=wp.int32),
        width: int,
        height: int,
        tile_size: int,
        tiles_x: int,
        tiles_per_camera: int,
        max_alpha: float,
        alphas: wp.array(dtype=float),
        last_ids: wp.array(dtype=wp.int32),
        v_render: wp.array(dtype=vecD),
        v_alphas: wp.array(dtype=float),
        out_grads: wp.array(dtype=vecF),
    ):
        tid = wp.tid()
        tile_area = tile_size * tile_size
        tile = tid / tile_area
        c, px, py = tile_pixel(tile, tid - tile * tile_area, tile_size, tiles_x, tiles_per_camera)
        if px >= width or py >= height:
            return
        pix = (c * height + py) * width + px
        start = tile_ranges[tile, 0]
        T_final = 1.0 - alphas[pix]
        T = T_final
        S = vecD()
        v_rgb = v_render[pix]
        v_alpha = v_alphas[pix]
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        i = last_ids[pix]
        while i >= start:
            m, con, o, col = array_row(splats, i)
            T, S, grad, touched = reverse_step(m, con, o, col, fx, fy, max_alpha, T, T_final, S, v_rgb, v_alpha)
            wp.atomic_add(out_grads, flatten_ids[i], grad)
            i -= 1

    row = SPLAT_SLOTS + channels

    @functools.cache
    def block_kernel(group: int):
        """Cooperative kernel of the deterministic reduction: one block per ``group`` pixels of a tile walks
        the list in lock step, batches of ``group`` rows copied to shared memory, sums each entry's gradient
        over the block and writes the sum to the entry's row (summed per Gaussian in a fixed order later)."""

        @wp.kernel(enable_backward=False, module="unique", module_options=COMPOSITE_OPTIONS)
        def composite_backward_blocks(
            splats: wp.array2d(dtype=float),
            tile_ranges: wp.array2d(dtype=wp.int32),
            flatten_ids: wp.array(dtype=wp.int32),
            width: int,
            height: int,
            tile_size: int,
            tiles_x: int,
            tiles_per_camera: int,
            max_alpha: float,
            alphas: wp.array(dtype=float),
            last_ids: wp.array(dtype=wp.int32),
            v_render: wp.array(dtype=vecD),
            v_alphas: wp.array(dtype=float),
            groups: int,
            out_rows: wp.array(dtype=vecF),
        ):
            block, lane = wp.tid()
            tile = block / groups
            block_group = block - tile * groups
            local = block_group * group + lane
            # Every lane takes part in the block reductions; lanes off the image or the tile stay idle.
            pix, last, fx, fy = walk_pixel(tile, local, tile_size, tiles_x, tiles_per_camera, width, height,
                                           last_ids)
            T_final = 1.0 - alphas[pix]
            T = T_final
            S = vecD()
            v_rgb = v_render[pix]
            v_alpha = v_alphas[pix]
            start = tile_ranges[tile, 0]
            i = wp.tile_max(wp.tile(last))[0]
            while i >= start:
                base = wp.max(start, i - (group - 1))
                batch = wp.tile_load(splats, shape=(group, row), offset=(base, 0), storage="shared")
                while i >= base:
                    grad = vecF()
                    hit = int(0)
                    if i <= last:
                        r = i - base
                        col = vecD()
                        for k in range(channels):
                            col[k] = batch[r, SPLAT_SLOTS + k]
                        T, S, grad, touched = reverse_step(wp.vec2(batch[r, 0], batch[r, 1]),
                                                           wp.vec3(batch[r, 2], batch[r, 3], batch[r, 4]),
                                                           batch[r, 5], col, fx, fy, max_alpha, T, T_final, S,
                                                           v_rgb, v_alpha)
                        if wp.length_sq(grad) > 0.0:
                            hit = 1
                    # A cheap integer reduction first: most entries touch none of a group's pixels.
                    if wp.tile_max(wp.tile(hit))[0] > 0:
                        total = wp.tile_sum(wp.tile(grad, preserve_type=True))[0]
                        if lane == 0:
                            out_rows[i * groups + block_group] = total
                    i -= 1

        return composite_backward_blocks

    sum_add = lanes_sum_add(channels + SPLAT_GRAD_SLOTS)
    splat_batch = splat_batch_func(LANES, channels)

    @wp.kernel(enable_backward=False, module="unique", module_options=COMPOSITE_OPTIONS)
    def composite_backward_lanes(
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=vecD),
        tile_ranges: wp.array2d(dtype=wp.int32),
        flatten_ids: wp.array(dtype=wp.int32),
        width: int,
        height: int,
        tile_size: int,
        tiles_x: int,
        tiles_per_camera: int,
        max_alpha: float,
        alphas: wp.array(dtype=float),
        last_ids: wp.array(dtype=wp.int32),
        v_render: wp.array(dtype=vecD),
        v_alphas: wp.array(dtype=float),
        groups: int,
        out_grads: wp.array(dtype=vecF),
    ):
        # One block = one warp = LANES pixels of a tile; see the module docstring ("warp").
        block, lane = wp.tid()
        tile = block / groups
        local = (block - tile * groups) * LANES + lane
        # Every lane takes part in the warp operations; lanes off the image or the tile stay idle.
        pix, last, fx, fy = walk_pixel(tile, local, tile_size, tiles_x, tiles_per_camera, width, height, last_ids)
        T_final = 1.0 - alphas[pix]
        T = T_final
        S = vecD()
        v_rgb = v_render[pix]
        v_alpha = v_alphas[pix]
        start = tile_ranges[tile, 0]
        x0, x1, y0, y1 = lanes_box(tile, local - lane, LANES, tile_size, tiles_x, tiles_per_camera)
        i = lanes_max(last)
        while i >= start:
            base = wp.max(start, i - (LANES - 1))
            xy, con, opa, col = splat_batch(flatten_ids, base, means2d, conics, opacities, colors)
            # Lane k bounds entry base + k against the warp's pixels; the entries it rules out touch none of
            # them (no T, S or gradient change), so the walk skips them (module docstring).
            near = lanes_ballot(may_touch(xy[lane], con[lane], opa[lane], x0, x1, y0, y1), lane)
            r = highest_bit(near, i - base)
            while r >= 0:
                i = base + r
                grad = vecF()
                touched = int(0)
                if i <= last:
                    T, S, grad, touched = reverse_step(xy[r], con[r], opa[r], col[r], fx, fy, max_alpha, T, T_final,
                                                       S, v_rgb, v_alpha)
                # Many entries still touch none of a warp's pixels: one vote skips their reduction and atomics.
                if lanes_any(touched) != 0:
                    sum_add(grad, out_grads, flatten_ids[i], lane)
                r = highest_bit(near, r - 1)
            i = base - 1

    @wp.kernel(enable_backward=False, module="unique")
    def gather_rows(
        order: wp.array(dtype=wp.int32),
        segment_start: wp.array(dtype=wp.int32),
        groups: int,
        rows: wp.array(dtype=vecF),
        out_grads: wp.array(dtype=vecF),
    ):
        gid = wp.tid()
        acc = vecF()
        for j in range(segment_start[gid], segment_start[gid + 1]):
            base = order[j] * groups
            for s in range(groups):
                acc = acc + rows[base + s]
        out_grads[gid] = acc

    return composite_backward_atomic, block_kernel, composite_backward_lanes, gather_rows


def composite_backward(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    bins: Bins,
    width: int,
    height: int,
    tile_size: int,
    max_alpha: float,
    alphas: torch.Tensor,
    last_ids: torch.Tensor,
    v_render: torch.Tensor,
    v_alphas: torch.Tensor,
    deterministic: bool = False,
    reduction: str | None = None,
) -> torch.Tensor:
    """Packed splat gradients [C, N, 6 + D] (see ``unpack_splat_grads``) of a compositing pass.

    Inputs are those of ``composite.composite_forward`` plus its outputs ``alphas`` [C,H,W,1] and
    ``last_ids`` [C,H,W], and the cotangents ``v_render`` [C,H,W,D], ``v_alphas`` [C,H,W,1].
    ``deterministic=True`` gives bit-reproducible sums (see the module docstring for the cost);
    ``reduction`` ("pixel", "warp", "rows") overrides the choice (tests run every one on the CPU).
    """
    C, N, D = colors.shape
    F = D + SPLAT_GRAD_SLOTS
    grads = torch.zeros(C, N, F, device=colors.device, dtype=torch.float32)
    M = bins.flatten_ids.numel()
    if C == 0 or N == 0 or M == 0:
        return grads
    atomic_kernel, block_kernel, lanes_kernel, gather_kernel = _kernels(D)
    vecD, vecF = vector_type(D), vector_type(F)
    tiles_per_camera = bins.tiles_x * bins.tiles_y
    HW = C * height * width
    if reduction is None:
        reduction = "rows" if deterministic else "pixel" if colors.device.type == "cpu" else "warp"
    P = C * N
    if reduction != "warp":  # depth-sorted rows, gathered once (the deterministic blocks read them too)
        splats = [to_wp(gather_splats(means2d, conics, colors, opacities, bins.flatten_ids))]
    else:  # warps gather batches of splats through their ids
        splats = [to_wp(means2d, wp.vec2, (P,)), to_wp(conics, wp.vec3, (P,)), to_wp(opacities, None, (P,)),
                  to_wp(colors, vecD, (P,))]
    common = [
        *splats, to_wp(bins.tile_ranges), to_wp(bins.flatten_ids), int(width), int(height), int(tile_size),
        bins.tiles_x, tiles_per_camera, float(max_alpha), to_wp(alphas, None, (HW,)), to_wp(last_ids, None, (HW,)),
        to_wp(v_render, vecD, (HW,)), to_wp(v_alphas, None, (HW,)),
    ]
    if reduction == "pixel":
        launch(atomic_kernel, C * tiles_per_camera * tile_size * tile_size,
               [*common, to_wp(grads, vecF, (P,))], colors)
        return grads
    area = tile_size * tile_size
    if reduction == "warp":
        groups = -(-area // LANES)
        launch(lanes_kernel, C * tiles_per_camera * groups, [*common, groups, to_wp(grads, vecF, (P,))], colors,
               block_dim=LANES)
        return grads
    group_size = min(area, DETERMINISTIC_BLOCK)
    groups = -(-area // group_size)
    rows = torch.zeros(M * groups, F, device=colors.device, dtype=torch.float32)
    launch(block_kernel(group_size), C * tiles_per_camera * groups, [*common, groups, to_wp(rows, vecF)], colors,
           block_dim=group_size)
    ids = bins.flatten_ids.long()
    order = torch.sort(ids, stable=True).indices.to(torch.int32)
    segment_start = torch.zeros(C * N + 1, device=colors.device, dtype=torch.int64)
    segment_start[1:] = torch.cumsum(torch.bincount(ids, minlength=C * N), 0)
    launch(gather_kernel, C * N,
           [to_wp(order), to_wp(segment_start.to(torch.int32)), groups, to_wp(rows, vecF),
            to_wp(grads, vecF, (P,))],
           colors)
    return grads


def unpack_splat_grads(grads: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split packed [C, N, 6 + D] gradients into (d means2d [C,N,2], d conics [C,N,3], d colours [C,N,D],
    d opacities [C,N])."""
    return grads[..., 0:2], grads[..., 2:5], grads[..., SPLAT_GRAD_SLOTS:], grads[..., 5]
