"""The Warp rasteriser: the only room that imports Warp. Both packages render through ``rasterization``."""

from scenesplat_stereo.raster.rendering import RASTERIZE_MODES, RENDER_MODES, rasterization
from scenesplat_stereo.raster.tiling import check_device, tile_size_for

__all__ = ["rasterization", "RENDER_MODES", "RASTERIZE_MODES", "check_device", "tile_size_for"]
