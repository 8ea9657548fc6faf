"""SceneSplat-Stereo: render calibrated stereo pairs and nearby targets from 3DGS teacher scenes.

Rooms (see docs/architecture.md): ``gaussians`` (teacher .ply I/O), ``cameras`` (conventions),
``raster`` (the Warp rasteriser, the only room that imports Warp), ``teachers``, ``protocol``,
``shards``, ``build``, ``effects``, ``demo``, ``bench``, ``cli``.
"""

__version__ = "0.1.0"
