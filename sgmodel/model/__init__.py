"""The network: ``network`` (``StereoGaussians``, ``create_model``, ``load_predictor``), its parts (``layers``,
``decoder``, ``canvas``, ``predictor``, ``composer``, ``geometry``), ``render`` (the one door to the
rasteriser), ``checkpoint`` and the baselines without learning (``baselines``: naive-GS, forward-splat).

Public names: ``network.StereoGaussians``, ``network.create_model``, ``network.load_predictor``.
"""
