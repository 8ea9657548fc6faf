"""Tile binning: per-tile, depth-sorted lists of the Gaussians that can touch each tile.

Each (camera, Gaussian) writes one 64-bit key per tile of its rectangle, at an offset given by an
exclusive scan of the tile counts: key = (camera * tiles + tile) << 32 | bits(depth). Depths are
positive float32 (> near_plane), whose bit patterns sort like the floats. One stable radix sort over the
bits in use orders every tile's list front to back, with ties in Gaussian index order (the keys are
written in index order and the sort is stable). Tile ranges are then found where the tile part of
consecutive keys changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from ._warp import on_device_of, to_wp
from .projection import Projection


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
):
    c, g = wp.tid()
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


def bin_gaussians(proj: Projection, width: int, height: int, tile_size: int) -> Bins:
    """Build the per-tile sorted lists of a projection (one host sync: the total intersection count).
    Only the total waits for the GPU; everything else of the pass is queued after it without torch ops."""
    C, N = proj.depths.shape
    device = proj.depths.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = C * tiles_x * tiles_y
    ranges = torch.zeros(max(n_tiles, 1), 2, device=device, dtype=torch.int32)  # empty tiles stay (0, 0)
    if C * N == 0:
        return Bins(ranges[:n_tiles], torch.zeros(0, device=device, dtype=torch.int32), tiles_x, tiles_y)
    # Inclusive int64 scan (no overflow). The kernel arguments are built before the one host sync (the total,
    # to size the key buffers), while the GPU still runs the earlier stages, so little host work follows it.
    ends = torch.cumsum(proj.tiles_touched.reshape(-1), 0)
    key_inputs = [to_wp(proj.tile_rects, wp.vec4i), to_wp(proj.tiles_touched), to_wp(ends, shape=(C, N)),
                  to_wp(proj.depths.view(torch.int32)), tiles_x, tiles_x * tiles_y]
    ranges_arg = to_wp(ranges)
    # Sort only the bits in use: 32 of depth below the tile index of the last tile.
    end_bit = 32 + max(1, int(n_tiles - 1).bit_length())
    total = int(ends[-1])
    if total >= 2**31:
        raise RuntimeError(f"{total} tile intersections exceed int32 indexing; render fewer cameras per call")
    if total == 0:
        return Bins(ranges[:n_tiles], torch.zeros(0, device=device, dtype=torch.int32), tiles_x, tiles_y)
    keys = torch.empty(2 * total, device=device, dtype=torch.int64)  # the sort's double buffers
    values = torch.empty(2 * total, device=device, dtype=torch.int32)
    with on_device_of(keys) as dev:
        wp.launch(_write_keys, dim=(C, N), inputs=key_inputs, outputs=[to_wp(keys), to_wp(values)], device=dev)
        wk, wv = wp.from_torch(keys), wp.from_torch(values)
        wp.utils.radix_sort_pairs(wk, wv, total, begin_bit=0, end_bit=end_bit)
        wp.launch(_tile_ranges, dim=total, inputs=[wk, total], outputs=[ranges_arg], device=dev)
    return Bins(ranges[:n_tiles], values[:total], tiles_x, tiles_y)
