"""StereoGaussians model: frozen stereo encoder + DPT decoder + two-layer Gaussian predictor.

The model's rooms (data, encoders, decoder, predictor, composer, losses, train) arrive with their own
issues; today this package holds the command-line entry point, which lists what is available.
It renders through ``scenesplat_stereo.raster.rasterization``, the same function the dataset uses.
"""

__version__ = "0.1.0"
