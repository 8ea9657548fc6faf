"""Front-to-back alpha compositing of the binned Gaussians (SPEC section 2, steps 6-8).

Each tile intersection names its (camera, Gaussian) pair through ``flatten_ids``; its splat is the pair's
mean2d, conic, effective opacity and D colours. Two compiled variants of the same per-splat step:
- cooperative (default on CUDA): one thread block per tile, one thread per pixel; a batch of one list entry
  per thread at a time, the block gathers the entries' splats through their ids from the per-pair tensors
  [C * N, ...] into shared memory (``splat_batch_func``, one id lookup per splat per block, nothing written to
  global memory first; the cooperative backward kernels gather the same way) and every thread walks the
  batch there; the block stops when all its pixels are done. A tile's list holds every splat that reaches
  the tile, and a warp's pixels (a few rows of it) may miss many of them: the batch carries each entry's
  touch box (``projection.touch_extent``, conservative; written once per pair by the projection, as the
  block computing it for every batch made this kernel up to 12% slower on real captures), each warp tests
  the batch's boxes against its pixels (one entry per lane) and votes (blocks of at most ``VOTE_WARPS``
  warps). Where fewer than 1 / ``DENSE_DIVISOR`` of the entries are left (small splats, as in trained
  teachers), its threads walk only those; else every entry, in a plain loop (real captures of large splats,
  where a kernel that always walked the bits took 16-33% longer: docs/benchmarks.md). An entry ruled out
  touches none of the warp's pixels: the same image either way;
- per pixel (default on the CPU, where Warp runs threads serially and shared memory buys nothing): one
  thread per pixel walks its tile's list in depth-sorted splat rows [M, 6 + D] gathered once
  (``gather_splats``, which the per-pixel backward reads too; on the CPU contiguous rows beat an id
  lookup per splat per pixel).
Both are compiled per channel count D (RGB: 3, RGB+D: 4, D: 1, plain colours: any D): depth is one more
channel, so a render without depth does no depth work. Outputs are the raw sums (no background):
render = sum alpha_i T_i c_i, alpha = 1 - T, and the index (into ``flatten_ids``) of the last
composited Gaussian per pixel, -1 where none, for the backward pass.
"""

# No ``from __future__ import annotations``: Warp evaluates annotations, and those naming the per-D vector
# type of the kernel factory must be real objects, not strings.
import functools

import torch
import warp as wp

from scenesplat_stereo.raster._warp import ALPHA_MIN, T_MIN, launch, to_wp, vector_type
from scenesplat_stereo.raster.binning import Bins
from scenesplat_stereo.raster.lanes import LANES, bit_count, block_all, lanes_ballot, lowest_bit
from scenesplat_stereo.raster.projection import touch_extent

# CUDA compile options of the compositing kernels (forward and backward alike, so both make the same
# touch / stop decisions): fast math turns exp into the hardware approximation gsplat uses (__expf);
# measured in docs/benchmarks.md. CPU builds ignore it.
COMPOSITE_OPTIONS = {"fast_math": True}

# Leading slots of a splat row: mean2d (2, pixels), conic (3), effective opacity (1); then D colours.
SPLAT_SLOTS = 6


@wp.func
def tile_pixel(tile: int, local: int, tile_size: int, tiles_x: int, tiles_per_camera: int):
    """(camera, px, py) of pixel ``local`` (row-major within the tile) of tile ``tile`` (camera-major
    global tile index); px, py may lie past the image edge for edge tiles."""
    c = tile / tiles_per_camera
    t = tile - c * tiles_per_camera
    return c, (t % tiles_x) * tile_size + local % tile_size, (t / tiles_x) * tile_size + local / tile_size


@wp.func
def conic_sigma(dx: float, dy: float, a: float, b: float, c: float) -> float:
    """sigma = 0.5 delta^T [[a, b], [b, c]] delta at offset delta = (dx, dy) = mean2d - pixel centre, the
    exponent of alpha = o exp(-sigma) (SPEC step 6). The one expression every compositing kernel, forward
    and backward, evaluates, so they all make the same touch and stop decisions."""
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


@wp.func
def touch_alpha(xy: wp.vec2, conic: wp.vec3, opacity: float, fx: float, fy: float) -> float:
    """o exp(-sigma) of a splat (mean2d ``xy``, ``conic``, effective ``opacity``) at pixel centre (fx, fy)
    when it touches the pixel (sigma >= 0 and o exp(-sigma) >= 1/255, SPEC step 6), else 0."""
    sigma = conic_sigma(xy[0] - fx, xy[1] - fy, conic[0], conic[1], conic[2])
    if not (sigma >= 0.0):
        return 0.0
    alpha = opacity * wp.exp(-sigma)
    if not (alpha >= ALPHA_MIN):
        return 0.0
    return alpha


#: A batch is dense for a warp when at least 1 / DENSE_DIVISOR of its entries may touch the warp's pixels: the
#: warp then walks every entry in a plain loop, which costs less than walking the vote's bits one by one.
DENSE_DIVISOR = 2
#: Most warps a voting block has (16 x 16 tiles: 8): with 32 (32 x 32 tiles, 1,024 threads) the vote's masks take
#: more registers than a block of 1,024 threads may have (CUDA refuses the launch), so such blocks do not vote.
VOTE_WARPS = 8

@wp.func
def may_touch_box(xy: wp.vec2, extent: wp.vec2, x0: float, x1: float, y0: float, y1: float) -> int:
    """0 only when the box of half-widths ``extent`` (``projection.touch_extent``) around ``xy`` misses every pixel
    centre in [x0, x1] x [y0, y1] (pixels), so that the splat certainly touches none of them; else 1 (also for NaN
    means)."""
    if xy[0] + extent[0] < x0 or xy[0] - extent[0] > x1 or xy[1] + extent[1] < y0 or xy[1] - extent[1] > y1:
        return 0
    return 1


@wp.func
def may_touch(xy: wp.vec2, conic: wp.vec3, opacity: float, x0: float, x1: float, y0: float, y1: float) -> int:
    """0 only when the splat certainly touches no pixel centre in [x0, x1] x [y0, y1] (pixels), else 1: its
    ``touch_extent`` box against the pixels (``may_touch_box``), computed here (the compositing backward, whose
    batches of 32 took 8-10% longer when they gathered the projection's boxes instead)."""
    return may_touch_box(xy, touch_extent(conic, opacity), x0, x1, y0, y1)


@wp.func
def lanes_box(tile: int, first: int, count: int, tile_size: int, tiles_x: int, tiles_per_camera: int):
    """Pixel-centre bounds (x0, x1, y0, y1) of pixels ``first`` .. ``first + count - 1`` (row-major) of
    ``tile``; may reach past the image edge (a wider box only rules out less)."""
    _c0, x0, y0 = tile_pixel(tile, first, tile_size, tiles_x, tiles_per_camera)
    _c1, x1, y1 = tile_pixel(tile, wp.min(first + count, tile_size * tile_size) - 1, tile_size, tiles_x,
                            tiles_per_camera)
    if y1 != y0:  # more than one row: whole rows of the tile
        x0 = x0 - first % tile_size
        x1 = x0 + tile_size - 1
    return float(x0) + 0.5, float(x1) + 0.5, float(y0) + 0.5, float(y1) + 0.5


@functools.cache
def _gather_kernel(channels: int):
    vecD = vector_type(channels)

    @wp.kernel(enable_backward=False, module="unique")
    def gather(
        flatten_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=vecD),
        out_splats: wp.array2d(dtype=float),
    ):
        i = wp.tid()
        g = flatten_ids[i]
        m = means2d[g]
        con = conics[g]
        col = colors[g]
        out_splats[i, 0] = m[0]
        out_splats[i, 1] = m[1]
        out_splats[i, 2] = con[0]
        out_splats[i, 3] = con[1]
        out_splats[i, 4] = con[2]
        out_splats[i, 5] = opacities[g]
        for k in range(channels):
            out_splats[i, SPLAT_SLOTS + k] = col[k]

    return gather


def gather_splats(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
                  flatten_ids: torch.Tensor) -> torch.Tensor:
    """Depth-sorted splat rows [M, 6 + D] of the intersection list (see the module docstring), written in
    one pass from the per-(camera, Gaussian) tensors [C, N, ...] (the per-pixel forward and backward read
    these)."""
    C, N, D = colors.shape
    M = flatten_ids.numel()
    splats = torch.empty(M, SPLAT_SLOTS + D, device=colors.device, dtype=torch.float32)
    launch(_gather_kernel(D), M,
           [to_wp(flatten_ids), to_wp(means2d, wp.vec2, (C * N,)), to_wp(conics, wp.vec3, (C * N,)),
            to_wp(opacities, None, (C * N,)), to_wp(colors, vector_type(D), (C * N,)), to_wp(splats)],
           colors)
    return splats


@functools.cache
def splat_batch_func(size: int, channels: int, boxes: bool = False):
    """A Warp function for cooperative blocks: the splats (mean2d, conic, opacity, D colours; with ``boxes`` also
    the touch box, an ``extents`` argument after ``colors``) of the list entries base .. base + size - 1, gathered
    through their ids from the per-pair arrays into shared memory, one entry per thread. Entries past the list's
    end are other tiles' entries or, past the array, read as 0: valid splats that the caller never walks. The
    gathers go to registers first, with no barrier between them, so their loads are in flight together; then
    each is copied to shared memory for every thread to read. Every thread of the block must call it. The
    forward's batches gather the boxes; the backward's batches of 32 compute them (``may_touch``): gathering
    them there took 8-10% longer. One gather for both, taking the shared id tile as an argument, lost most of
    the forward's gain and slowed the backward by 1-6% (docs/benchmarks.md)."""
    vecD = vector_type(channels)

    if boxes:
        @wp.func
        def splat_box_batch(flatten_ids: wp.array(dtype=wp.int32), base: int, means2d: wp.array(dtype=wp.vec2),
                            conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float),
                            colors: wp.array(dtype=vecD), extents: wp.array(dtype=wp.vec2)):
            ids = wp.tile_load(flatten_ids, shape=(size,), offset=(base,), storage="shared")
            xy_r = wp.tile_load_indexed(means2d, indices=ids, shape=(size,), axis=0)
            con_r = wp.tile_load_indexed(conics, indices=ids, shape=(size,), axis=0)
            opa_r = wp.tile_load_indexed(opacities, indices=ids, shape=(size,), axis=0)
            col_r = wp.tile_load_indexed(colors, indices=ids, shape=(size,), axis=0)
            ext_r = wp.tile_load_indexed(extents, indices=ids, shape=(size,), axis=0)
            xy = wp.tile_empty(shape=(size,), dtype=wp.vec2, storage="shared")
            con = wp.tile_empty(shape=(size,), dtype=wp.vec3, storage="shared")
            opa = wp.tile_empty(shape=(size,), dtype=float, storage="shared")
            col = wp.tile_empty(shape=(size,), dtype=vecD, storage="shared")
            ext = wp.tile_empty(shape=(size,), dtype=wp.vec2, storage="shared")
            wp.tile_assign(xy, xy_r)
            wp.tile_assign(con, con_r)
            wp.tile_assign(opa, opa_r)
            wp.tile_assign(col, col_r)
            wp.tile_assign(ext, ext_r)
            return xy, con, opa, col, ext

        return splat_box_batch

    @wp.func
    def splat_batch(flatten_ids: wp.array(dtype=wp.int32), base: int, means2d: wp.array(dtype=wp.vec2),
                    conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float), colors: wp.array(dtype=vecD)):
        ids = wp.tile_load(flatten_ids, shape=(size,), offset=(base,), storage="shared")
        xy_r = wp.tile_load_indexed(means2d, indices=ids, shape=(size,), axis=0)
        con_r = wp.tile_load_indexed(conics, indices=ids, shape=(size,), axis=0)
        opa_r = wp.tile_load_indexed(opacities, indices=ids, shape=(size,), axis=0)
        col_r = wp.tile_load_indexed(colors, indices=ids, shape=(size,), axis=0)
        xy = wp.tile_empty(shape=(size,), dtype=wp.vec2, storage="shared")
        con = wp.tile_empty(shape=(size,), dtype=wp.vec3, storage="shared")
        opa = wp.tile_empty(shape=(size,), dtype=float, storage="shared")
        col = wp.tile_empty(shape=(size,), dtype=vecD, storage="shared")
        wp.tile_assign(xy, xy_r)
        wp.tile_assign(con, con_r)
        wp.tile_assign(opa, opa_r)
        wp.tile_assign(col, col_r)
        return xy, con, opa, col

    return splat_batch


@functools.cache
def composite_kernel(channels: int, tile_size: int, cooperative: bool):
    """The compositing kernel for ``channels`` colour channels and ``tile_size`` square tiles. The
    cooperative variant reads splats through ``flatten_ids`` from the per-pair arrays (P = C * N pairs:
    means2d [P] vec2, conics [P] vec3, opacities [P], colors [P] of D-vectors); the per-pixel variant reads
    the depth-sorted rows of ``gather_splats``; the cooperative one also the pairs' touch boxes ``extents`` [P]
    vec2 (``Projection.touch_extents``), on which its warps vote."""
    block = tile_size * tile_size
    vecD = vector_type(channels)
    splat_batch = splat_batch_func(block, channels, boxes=True)

    # Blocks of whole warps, at most VOTE_WARPS of them, vote per warp on the batch's entries (their touch boxes
    # against the warp's pixels) and walk only those left where few are; other blocks walk every entry.
    warps = block // LANES if block % LANES == 0 and block // LANES <= VOTE_WARPS else 0
    vecW = wp.types.vector(length=max(warps, 1), dtype=wp.int32)  # the warp's vote masks, one per LANES entries

    @wp.func
    def front_step(xy: wp.vec2, con: wp.vec3, opa: float, col: vecD, fx: float, fy: float, max_alpha: float,
                   T: float, acc: vecD, last: int, i: int):
        """Composite list entry ``i`` at pixel centre (fx, fy): (T, acc, last, 1 if compositing stops here)."""
        vis = touch_alpha(xy, con, opa, fx, fy)
        if vis == 0.0:
            return T, acc, last, 0
        alpha = wp.min(max_alpha, vis)
        next_T = T * (1.0 - alpha)
        if next_T <= T_MIN:
            return T, acc, last, 1
        w = alpha * T
        for k in range(channels):
            acc[k] = acc[k] + w * col[k]
        return next_T, acc, i, 0

    @wp.kernel(enable_backward=False, module="unique", module_options=COMPOSITE_OPTIONS)
    def composite_per_pixel(
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
        tid = wp.tid()
        tile = tid / block  # camera * tiles_per_camera + tile index
        c, px, py = tile_pixel(tile, tid - tile * block, tile_size, tiles_x, tiles_per_camera)
        if px >= width or py >= height:
            return
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        T = float(1.0)
        acc = vecD()
        last = int(-1)
        for i in range(tile_ranges[tile, 0], tile_ranges[tile, 1]):
            col = vecD()
            for k in range(channels):
                col[k] = splats[i, SPLAT_SLOTS + k]
            T, acc, last, stop = front_step(wp.vec2(splats[i, 0], splats[i, 1]),
                                            wp.vec3(splats[i, 2], splats[i, 3], splats[i, 4]), splats[i, 5], col, fx,
                                            fy, max_alpha, T, acc, last, i)
            if stop != 0:
                break
        pix = (c * height + py) * width + px
        out_render[pix] = acc
        out_alphas[pix] = 1.0 - T
        out_last[pix] = last

    @wp.kernel(enable_backward=False, module="unique", module_options=COMPOSITE_OPTIONS)
    def composite_cooperative(
        flatten_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=vecD),
        extents: wp.array(dtype=wp.vec2),
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
        c, px, py = tile_pixel(tile, lane, tile_size, tiles_x, tiles_per_camera)
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        done = int(0)
        if px >= width or py >= height:
            done = 1
        T = float(1.0)
        acc = vecD()
        last = int(-1)
        b = tile_ranges[tile, 0]
        end = tile_ranges[tile, 1]
        wl = lane % LANES
        x0, x1, y0, y1 = lanes_box(tile, lane - wl, LANES, tile_size, tiles_x, tiles_per_camera)
        while b < end:
            # Every thread reaches the cooperative calls; the block stops once all its pixels are done.
            if block_all(done) != 0:
                break
            xy, con, opa, col, ext = splat_batch(flatten_ids, b, means2d, conics, opacities, colors, extents)
            n = wp.min(block, end - b)
            masks = vecW()
            near = n  # without a vote (blocks smaller than a warp): every entry
            if wp.static(warps > 0):
                near = int(0)
                for w in range(warps):  # the warp's vote on entries w * LANES + wl (every lane votes)
                    k = w * LANES + wl
                    masks[w] = lanes_ballot(wp.where(k < n, may_touch_box(xy[k], ext[k], x0, x1, y0, y1), 0), wl)
                    near += bit_count(masks[w])
            if near * DENSE_DIVISOR < n:  # sparse: walk the vote's entries
                for w in range(warps):
                    r = lowest_bit(masks[w], 0)
                    while done == 0 and r >= 0:
                        j = w * LANES + r
                        T, acc, last, done = front_step(xy[j], con[j], opa[j], col[j], fx, fy, max_alpha, T, acc,
                                                        last, b + j)
                        r = lowest_bit(masks[w], r + 1)
            elif done == 0:  # dense (or no vote): walk every entry
                for j in range(n):
                    T, acc, last, done = front_step(xy[j], con[j], opa[j], col[j], fx, fy, max_alpha, T, acc, last,
                                                    b + j)
                    if done != 0:
                        break
            b += block
        if px < width and py < height:
            pix = (c * height + py) * width + px
            out_render[pix] = acc
            out_alphas[pix] = 1.0 - T
            out_last[pix] = last

    return composite_cooperative if cooperative else composite_per_pixel


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
    touch_extents: torch.Tensor,
    cooperative: bool | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite [C, N] screen-space Gaussians with colours [C, N, D] into (render [C,H,W,D] without
    background, alphas [C,H,W,1], last_ids [C,H,W] int32). ``touch_extents`` [C, N, 2] are the projection's
    (``Projection.touch_extents``; the cooperative variant's votes read them). ``cooperative`` picks the variant
    (default: cooperative on CUDA, per pixel on the CPU); both give the same image."""
    C, N, D = colors.shape
    dev = colors.device
    if C == 0 or N == 0 or bins.flatten_ids.numel() == 0 or width * height == 0:
        return (torch.zeros(C, height, width, D, device=dev), torch.zeros(C, height, width, 1, device=dev),
                torch.full((C, height, width), -1, device=dev, dtype=torch.int32))
    render = torch.empty(C, height, width, D, device=dev, dtype=torch.float32)
    alphas = torch.empty(C, height, width, 1, device=dev, dtype=torch.float32)
    last_ids = torch.empty(C, height, width, device=dev, dtype=torch.int32)
    if cooperative is None:  # a CUDA block holds at most 1024 threads: larger tiles go per pixel
        cooperative = dev.type == "cuda" and tile_size * tile_size <= 1024
    P = C * N
    vecD = vector_type(D)
    tiles_per_camera = bins.tiles_x * bins.tiles_y
    if cooperative:
        splats = [to_wp(bins.flatten_ids), to_wp(means2d, wp.vec2, (P,)), to_wp(conics, wp.vec3, (P,)),
                  to_wp(opacities, None, (P,)), to_wp(colors, vecD, (P,)), to_wp(touch_extents, wp.vec2, (P,))]
    else:
        splats = [to_wp(gather_splats(means2d, conics, colors, opacities, bins.flatten_ids))]
    args = [*splats, to_wp(bins.tile_ranges), int(width), int(height), bins.tiles_x, tiles_per_camera,
            float(max_alpha), to_wp(render, vecD, (C * height * width,)), to_wp(alphas, None, (C * height * width,)),
            to_wp(last_ids, None, (C * height * width,))]
    kernel = composite_kernel(D, tile_size, cooperative)
    if cooperative:
        launch(kernel, C * tiles_per_camera, args, colors, block_dim=tile_size * tile_size)
    else:
        launch(kernel, C * tiles_per_camera * tile_size * tile_size, args, colors)
    return render, alphas, last_ids
