"""The Warp rasteriser (one of the two folders that import Warp): both packages render through
``rasterization`` (gsplat's signature), and ``reference.py`` beside it is its independent float64 twin.

Public names: ``rasterization``, ``RENDER_MODES``, ``RASTERIZE_MODES``, ``check_device``, ``tile_size_for``. They
load on first use (PEP 562), so that importing the float64 reference loads neither the rasteriser nor Warp.
"""

import importlib

_PUBLIC = {"rasterization": "rendering", "RENDER_MODES": "rendering", "RASTERIZE_MODES": "rendering",
           "check_device": "tiling", "tile_size_for": "tiling"}

__all__ = list(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(importlib.import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
