"""Batches for training and evaluation: shards read into square-cropped pairs and targets (``loader``, with
``to_device``), the crop (``square_crop``), the resumable sample order (``sample_order``) and the frozen
encoder's outputs cached per pair (``encoder_cache``).

Public names: ``loader.make_loader``, ``loader.read_split``, ``encoder_cache.open_cache``.
"""
