"""The paper's dataset from teachers: the protocol's rules (``protocol``), stereo pairs and targets rendered
(``render_pairs``, ``effects``), the build command (``run``, ``settings``), ``render_teacher`` (the render
command), procedural rooms (``demo``) and the dataset's checks (``inspection``).

Public names: ``run.build``, ``settings.BuildSettings``, ``protocol.plan_scene``, ``inspection.inspect_dataset``.
"""
