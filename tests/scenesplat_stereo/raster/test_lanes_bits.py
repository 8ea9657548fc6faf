"""The bit-mask helpers of the compositing votes (scenesplat_stereo/raster/lanes.py): ``bit_count``,
``lowest_bit`` and ``highest_bit`` on 32-bit masks held in int32 (the sign bit is lane 31), against Python's
integers, on the CPU and on CUDA where there is one (their CUDA branches are intrinsics)."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from scenesplat_stereo.raster._warp import launch, to_wp
from scenesplat_stereo.raster.lanes import bit_count, highest_bit, lowest_bit

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
MASKS = [0, 1, 2, 0x80000000, 0xFFFFFFFF, 0x7FFFFFFF, 0x55555555, 0xAAAAAAAA, 0x00010000, 0xF000000F, 0x12345678]
STARTS = [-1, 0, 1, 5, 16, 30, 31, 32]


@wp.kernel(enable_backward=False)
def _bits(masks: wp.array(dtype=wp.int32), starts: wp.array(dtype=wp.int32), out: wp.array2d(dtype=wp.int32)):
    i, j = wp.tid()
    out[i, j * 3 + 0] = bit_count(masks[i])
    out[i, j * 3 + 1] = lowest_bit(masks[i], starts[j])
    out[i, j * 3 + 2] = highest_bit(masks[i], starts[j])


def _expected(mask: int, r: int) -> tuple[int, int, int]:
    set_bits = [k for k in range(32) if mask >> k & 1]
    low = min((k for k in set_bits if k >= r), default=-1) if r <= 31 else -1
    high = max((k for k in set_bits if k <= r), default=-1) if r >= 0 else -1
    return len(set_bits), low, high


@pytest.mark.parametrize("device", DEVICES)
def test_bit_helpers_match_python_integers(device):
    masks = torch.tensor([m - (1 << 32) if m >= 1 << 31 else m for m in MASKS], dtype=torch.int32, device=device)
    starts = torch.tensor(STARTS, dtype=torch.int32, device=device)
    out = torch.empty(len(MASKS), 3 * len(STARTS), dtype=torch.int32, device=device)
    launch(_bits, (len(MASKS), len(STARTS)), [to_wp(masks), to_wp(starts), to_wp(out)], masks)
    got = out.cpu().reshape(len(MASKS), len(STARTS), 3).tolist()
    for i, mask in enumerate(MASKS):
        for j, r in enumerate(STARTS):
            assert tuple(got[i][j]) == _expected(mask, r), f"mask {mask:#010x}, r = {r}"
