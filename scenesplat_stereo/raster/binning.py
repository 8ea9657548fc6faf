"""Tile binning: per-tile, depth-sorted lists of the Gaussians that can touch each tile.

Each (camera, Gaussian) writes one 64-bit key per tile of its rectangle, at an offset given by an
exclusive scan of the tile counts: key = (camera * tiles + tile) << 32 | bits(depth). Depths are
positive float32 (> near_plane), whose bit patterns sort like the floats. One stable radix sort over the
bits in use orders every tile's list front to back, with ties in Gaussian index order (the keys are
written in index order and the sort is stable). Tile ranges are then found where the tile part of
consecutive keys changes. The total of the scan sizes the key buffers: the pass's one host sync, split
into ``start_binning`` (queue the scan and the total's copy) and ``finish_binning`` (wait, then the rest)
so that other device work can be queued in between.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from scenesplat_stereo.raster._warp import launch, radix_sort_pairs, to_wp
from scenesplat_stereo.raster.projection import Projection


@dataclass
class Bins:
    """Sorted tile lists. ``flatten_ids`` hold c * N + g; tile t of camera c is row c * tiles + t (for a batch
    of scenes, c is the flat camera index b * C + c of ``projection.project_gaussians``)."""

    tile_ranges: torch.Tensor  # [C * tiles_y * tiles_x, 2] int32 (start, end) into flatten_ids
    flatten_ids: torch.Tensor  # [M] int32
    tiles_x: int
    tiles_y: int


@wp.kernel(enable_backward=False)
def _write_keys(
    rects: wp.array2d(dtype=wp.vec4i),
    tiles_touched: wp.array2d(dtype=wp.int32),
    ends: wp.array2d(dtype=wp.int64),
    depth_bits: wp.array2d(dtype=wp.int32),
    tiles_x: int,
    tiles_per_camera: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
    ranges: wp.array2d(dtype=wp.int32),
):
    c, g = wp.tid()
    # Empty tiles keep the range (0, 0): the threads clear the ranges first (``_tile_ranges`` runs after the
    # sort), thread c * N + g every (C * N)-th tile from its own index.
    t = c * rects.shape[1] + g
    while t < ranges.shape[0]:
        ranges[t, 0] = 0
        ranges[t, 1] = 0
        t += rects.shape[0] * rects.shape[1]
    count = tiles_touched[c, g]
    if count == 0:  # culled or off-screen: no keys, and no need to read the rectangle
        return
    k = int(ends[c, g] - wp.int64(count))  # exclusive offset from the inclusive scan (< 2^31, checked)
    r = rects[c, g]
    value = c * rects.shape[1] + g
    zbits = wp.int64(depth_bits[c, g])
    for ty in range(r[1], r[3] + 1):
        for tx in range(r[0], r[2] + 1):
            tile = wp.int64(c * tiles_per_camera + ty * tiles_x + tx)
            keys[k] = (tile << wp.int64(32)) | zbits
            values[k] = value
            k += 1


@wp.kernel(enable_backward=False)
def _tile_ranges(keys: wp.array(dtype=wp.int64), count: int, ranges: wp.array2d(dtype=wp.int32)):
    # Entry i closes its tile's range where the next key's tile differs, and opens the next tile's there.
    i = wp.tid()
    tile = int(keys[i] >> wp.int64(32))
    if i == 0:
        ranges[tile, 0] = 0
    if i == count - 1:
        ranges[tile, 1] = count
    else:
        following = int(keys[i + 1] >> wp.int64(32))
        if following != tile:
            ranges[tile, 1] = i + 1
            ranges[following, 0] = i + 1


@dataclass
class PendingBins:
    """A started binning pass (``start_binning``): the scan is queued on the device and its total, which
    sizes the key buffers, is on its way to the host; the kernel arguments that do not depend on it are
    built."""

    C: int
    N: int
    tiles_x: int
    tiles_y: int
    ranges: torch.Tensor  # [max(tiles, 1), 2] int32, cleared by ``_write_keys`` (empty tiles stay (0, 0))
    total: torch.Tensor | None  # [1] int64 on the host (pinned, filled once ``ready``), None: nothing to bin
    ready: torch.cuda.Event | None  # recorded after the copy of the total on CUDA, None on the CPU
    key_inputs: list
    end_bit: int  # sort bits [0, end_bit): 32 of depth below the tile index of the last tile


def start_binning(proj: Projection, width: int, height: int, tile_size: int) -> PendingBins:
    """Queue the inclusive int64 scan of the tile counts (no overflow) and the copy of its total to the
    host, without waiting for either: work queued after this (the SH colours in ``rasterization``) keeps
    the GPU busy while ``finish_binning`` waits for the total and issues the rest of the pass."""
    C, N = proj.depths.shape
    device = proj.depths.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = C * tiles_x * tiles_y
    ranges = torch.empty(max(n_tiles, 1), 2, device=device, dtype=torch.int32)
    pending = PendingBins(C, N, tiles_x, tiles_y, ranges, None, None, [],
                          32 + max(1, int(n_tiles - 1).bit_length()))
    if C * N == 0:
        return pending
    ends = torch.cumsum(proj.tiles_touched.reshape(-1), 0)
    if device.type == "cuda":
        pending.total = ends[-1:].to("cpu", non_blocking=True)  # into pinned host memory
        pending.ready = torch.cuda.Event()
        pending.ready.record(torch.cuda.current_stream(device))
    else:
        pending.total = ends[-1:]
    pending.key_inputs = [to_wp(proj.tile_rects, wp.vec4i), to_wp(proj.tiles_touched), to_wp(ends, shape=(C, N)),
                          to_wp(proj.depths.view(torch.int32)), tiles_x, tiles_x * tiles_y]
    return pending


def finish_binning(pending: PendingBins) -> Bins:
    """Wait for the total intersection count (the pass's one host sync), then write the keys, sort them
    and find the tile ranges."""
    p = pending
    n_tiles = p.C * p.tiles_x * p.tiles_y
    device = p.ranges.device
    if p.ready is not None:
        p.ready.synchronize()
    total = 0 if p.total is None else int(p.total[0])
    if total >= 2**31:
        raise RuntimeError(f"{total} tile intersections exceed int32 indexing; render fewer cameras per call")
    if total == 0:
        return Bins(p.ranges[:n_tiles].zero_(), torch.zeros(0, device=device, dtype=torch.int32), p.tiles_x, p.tiles_y)
    keys = torch.empty(2 * total, device=device, dtype=torch.int64)  # the sort's double buffers
    values = torch.empty(2 * total, device=device, dtype=torch.int32)
    launch(_write_keys, (p.C, p.N), [*p.key_inputs, to_wp(keys), to_wp(values), to_wp(p.ranges)], keys)
    radix_sort_pairs(keys, values, total, p.end_bit)
    launch(_tile_ranges, total, [to_wp(keys), total, to_wp(p.ranges)], keys)
    return Bins(p.ranges[:n_tiles], values[:total], p.tiles_x, p.tiles_y)


def bin_gaussians(proj: Projection, width: int, height: int, tile_size: int) -> Bins:
    """Build the per-tile sorted lists of a projection in one go (``start_binning`` then
    ``finish_binning``; one host sync: the total intersection count)."""
    return finish_binning(start_binning(proj, width, height, tile_size))
