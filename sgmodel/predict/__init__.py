"""From a stereo pair or video to scenes and views: the ``sgmodel predict`` command (``command``), the model
or a baseline applied (``inference``), stereo video (``video``), scene export and novel-view cameras
(``export``) and viewer settings (``viewers``).

Public names: ``inference.Reconstructor``, ``export.to_scene``, ``export.write_scene``.
"""
