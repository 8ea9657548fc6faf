"""A user's stereo input made model-ready: images (``stereo_pair``), calibration (``calib``, ``rig``),
rectification (``rectify``, also the ``sgmodel rectify`` command), the camera frame (``rotate``: the model's tensors turned with ``scenesplat_stereo.scene.transform``), the
left/right check (``stereo_check``) and the flags that read a pair (``prepare``).

Public names: ``stereo_pair.Pair``, ``calib.Calibration``, ``rectify.Rectification``.
"""
