"""Captured (not rendered) inputs turned into shards or poses: StereoNVS-Real (``stereonvs``, the command
``import stereonvs``), LLFF ``poses_bounds.npy`` (``llff``) and COLMAP pose recovery (``colmap``).

Public names: ``stereonvs.import_stereonvs``, ``llff.read_poses_bounds``, ``colmap``'s reconstruction helpers.
"""
