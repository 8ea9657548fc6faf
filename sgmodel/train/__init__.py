"""Training, from batches to checkpoints: the ``sgmodel train`` command (``command``), the loop (``loop``), the
objective (``losses``), several processes (``distributed``) and the encoder cache's command (``encode_cache``).

Public names: ``loop.train``, ``loop.train_step``, ``loop.TrainingDiverged``.
"""
