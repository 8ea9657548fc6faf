"""Rasteriser policy outside the kernels: which torch devices it renders on, and the tile edge for each.

The image does not depend on the tile edge (tests/scenesplat_stereo/raster/test_raster_forward.py: within 1e-5 across tile sizes);
the time does.
"""

from __future__ import annotations

import torch


def tile_size_for(device: str | torch.device) -> int:
    """Tile edge in pixels for rendering on ``device``. Warp runs CPU kernels serially, so shorter per-tile
    lists win there (8 px: 3.4x faster than 16 at 320x180, docs/benchmarks.md); on CUDA 16 px (gsplat's
    default) keeps 256-thread blocks."""
    return 8 if torch.device(device).type == "cpu" else 16


def check_device(text: str, flag: str = "--device") -> str:
    """``text`` if the rasteriser can render on it ("cpu", "cuda", "cuda:<n>" with that GPU present);
    ValueError naming ``flag`` otherwise."""
    try:
        device = torch.device(text)
    except (RuntimeError, TypeError):
        raise ValueError(f"{flag} {text!r}: expected cpu, cuda or cuda:<n>") from None
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"{flag} {text!r}: the rasteriser runs on cpu or cuda only")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{flag} {text}: no CUDA device is available to torch")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"{flag} {text}: only {torch.cuda.device_count()} CUDA devices")
    return str(text)
