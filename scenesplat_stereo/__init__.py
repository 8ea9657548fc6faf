"""SceneSplat-Stereo: render calibrated stereo pairs and nearby targets from 3DGS teacher scenes.

Stages, bottom-up as the data flows (docs/architecture.md): ``common`` (files, the command line's one error
path, text), ``scene`` (a 3DGS scene on disk, the teacher), ``raster`` (the Warp rasteriser and its float64
twin), ``shards`` (the sample record and the WebDataset shards), ``build`` (the paper's protocol: samples
rendered from teachers), ``captured`` (captured, not rendered, inputs), ``bench``; ``cli`` is the command table.
"""

__version__ = "0.1.0"
