"""From a stereo pair or video to scenes and views: the ``sgmodel predict`` command (``command``), the model
or a baseline applied (``inference``), stereo video (``video``), the scene to the host and novel-view cameras
(``export``), scene files and the processes writing one per frame (``scene_writers``) and viewer settings
(``viewers``).

Public names: ``inference.Reconstructor``, ``export.to_scene``, ``scene_writers.write_scene``.
"""
