"""A 3DGS scene on disk, and the teacher it becomes: one owner per file format (``ply``, ``gaussians`` for the
INRIA layout, ``compressed_ply``, ``spz``), ``scene_files`` (any of them by its bytes), ``cameras``
(the conventions), ``harmonics`` (the SH colour basis), ``transform`` (a scene moved, turned and scaled),
``teachers`` (finding teacher folders and their trajectories) and ``row_tasks`` (the shared thread pool the
compact writers quantise on).

Public names: ``GaussianScene``, ``load_ply``/``save_ply``, ``scene_files.load_scene``/``save_scene``,
``teachers.discover_teachers``, ``transform.transform_scene``.
"""
