"""StereoGaussians model: frozen stereo encoder + DPT decoder + two-layer Gaussian predictor on a padded
canvas + residual attribute composer, trained by rendering targets through
``scenesplat_stereo.raster.rasterization`` (the same function the dataset uses).

Entry points: ``sgmodel.model.network.create_model`` / ``load_predictor``, ``sgmodel.train.loop.train``, and the
``sgmodel`` command (train, eval, predict, ablate, weights, bench). The rooms are listed in docs/model.md.
"""

__version__ = "0.1.0"
