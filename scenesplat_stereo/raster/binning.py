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
    offsets: wp.array2d(dtype=wp.int32),
    depth_bits: wp.array2d(dtype=wp.int32),
    tiles_x: int,
    tiles_per_camera: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    c, g = wp.tid()
    r = rects[c, g]
    n = rects.shape[1]
    k = offsets[c, g]
    zbits = wp.int64(depth_bits[c, g])
    for ty in range(r[1], r[3] + 1):
        for tx in range(r[0], r[2] + 1):
            tile = wp.int64(c * tiles_per_camera + ty * tiles_x + tx)
            keys[k] = (tile << wp.int64(32)) | zbits
            values[k] = c * n + g
            k += 1


@wp.kernel(enable_backward=False)
def _tile_ranges(keys: wp.array(dtype=wp.int64), count: int, ranges: wp.array2d(dtype=wp.int32)):
    i = wp.tid()
    tile = int(keys[i] >> wp.int64(32))
    if i == 0:
        ranges[tile, 0] = i
    elif int(keys[i - 1] >> wp.int64(32)) != tile:
        ranges[tile, 0] = i
    if i == count - 1:
        ranges[tile, 1] = i + 1
    elif int(keys[i + 1] >> wp.int64(32)) != tile:
        ranges[tile, 1] = i + 1


def bin_gaussians(proj: Projection, width: int, height: int, tile_size: int) -> Bins:
    """Build the per-tile sorted lists of a projection (one host sync: the total intersection count)."""
    C, N = proj.depths.shape
    device = proj.depths.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = C * tiles_x * tiles_y
    ranges = torch.zeros(max(n_tiles, 1), 2, device=device, dtype=torch.int32)
    if C * N == 0:
        return Bins(ranges[:n_tiles], torch.zeros(0, device=device, dtype=torch.int32), tiles_x, tiles_y)
    # Inclusive int64 scan (no overflow), one host sync for the total to size the key buffers.
    ends = torch.cumsum(proj.tiles_touched.reshape(-1), 0)
    total = int(ends[-1])
    if total >= 2**31:
        raise RuntimeError(f"{total} tile intersections exceed int32 indexing; render fewer cameras per call")
    if total == 0:
        return Bins(ranges[:n_tiles], torch.zeros(0, device=device, dtype=torch.int32), tiles_x, tiles_y)
    offsets = (ends - proj.tiles_touched.reshape(-1)).to(torch.int32)
    keys = torch.empty(2 * total, device=device, dtype=torch.int64)
    values = torch.empty(2 * total, device=device, dtype=torch.int32)
    depth_bits = proj.depths.contiguous().view(torch.int32)
    end_bit = 32 + max(1, int(n_tiles - 1).bit_length())
    with on_device_of(keys) as dev:
        wp.launch(
            _write_keys,
            dim=(C, N),
            inputs=[
                to_wp(proj.tile_rects, wp.vec4i), to_wp(offsets.reshape(C, N)),
                to_wp(depth_bits), tiles_x, tiles_x * tiles_y,
            ],
            outputs=[to_wp(keys), to_wp(values)],
            device=dev,
        )
        wk, wv = wp.from_torch(keys), wp.from_torch(values)
        wp.utils.radix_sort_pairs(wk, wv, total, begin_bit=0, end_bit=end_bit)
        wp.launch(_tile_ranges, dim=total, inputs=[wk, total], outputs=[to_wp(ranges)], device=dev)
    return Bins(ranges[:n_tiles], values[:total], tiles_x, tiles_y)
