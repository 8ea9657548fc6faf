"""Tile binning (scenesplat_stereo/raster/binning.py): the tile ranges partition the sorted intersection list.

Checked from the outputs alone, for scenes that leave most tiles empty: every non-empty tile's range follows
the previous one without a gap and the last ends at the list's end, every entry of a tile's range is a
Gaussian seen by that tile's camera, in non-decreasing depth, and every empty tile's range is (0, 0) (the
ranges buffer is not zero-filled by torch: the key kernel clears it, so a stale buffer would show here).
"""

from __future__ import annotations

import pytest
import torch

from scenesplat_stereo.raster import rasterization
from tests.support.scenes import camera_rig, random_scene

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
W, H, TILE = 64, 48, 8


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("n", [1, 6, 200])
def test_tile_ranges_partition_the_sorted_list(n, device):
    C = 3
    scene = {k: v.to(device) for k, v in random_scene(n, seed=n, scale=(0.01, 0.05)).items()}
    viewmats, Ks = (t.to(device) for t in camera_rig(C, W, H, seed=n))
    tiles = (W // TILE) * (H // TILE)
    junk = torch.full((C * tiles, 2), 0x3F3F3F3F, dtype=torch.int32, device=device)
    del junk  # a freed buffer of the ranges' size, full of junk, for the allocator to hand out again
    _, _, meta = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                               scene["colors"], viewmats, Ks, W, H, tile_size=TILE)
    ranges, ids = meta["tile_ranges"].cpu(), meta["flatten_ids"].cpu().long()
    depths = meta["depths"].reshape(-1).cpu()
    assert ranges.shape == (C * tiles, 2)
    filled = ranges[:, 1] > ranges[:, 0]
    assert bool((ranges[~filled] == 0).all()), "an empty tile's range is not (0, 0)"
    assert int(filled.sum()) < C * tiles, "the scene should leave some tiles empty"
    spans = ranges[filled]
    if ids.numel() == 0:
        assert spans.numel() == 0
        return
    assert int(spans[0, 0]) == 0 and int(spans[-1, 1]) == ids.numel()
    assert torch.equal(spans[1:, 0], spans[:-1, 1]), "non-empty tiles' ranges must follow one another"
    for tile in torch.nonzero(filled)[:, 0].tolist():
        start, end = ranges[tile].tolist()
        entries = ids[start:end]
        assert bool((entries // n == tile // tiles).all()), f"tile {tile} lists another camera's Gaussian"
        assert bool((depths[entries][1:] >= depths[entries][:-1]).all()), f"tile {tile} not depth-sorted"
