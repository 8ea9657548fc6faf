"""StereoGaussians model: frozen stereo encoder + DPT decoder + two-layer Gaussian predictor on a padded
canvas + residual attribute composer, trained by rendering targets through
``scenesplat_stereo.raster.rasterization`` (the same function the dataset uses).

Stages, bottom-up as the data flows (docs/architecture.md): ``kernels``, ``encoders``, ``data`` (batches),
``model``, ``metrics``, ``train`` (checkpoints), ``pairs`` (a user's stereo input), ``predict`` (scenes),
``evaluation``, ``bench``; ``config``, ``args`` and ``weights`` are shared, ``cli`` is the command table.
Entry points: ``sgmodel.model.network.create_model`` / ``load_predictor``, ``sgmodel.train.loop.train``, and the
``sgmodel`` command.
"""

__version__ = "0.1.0"
