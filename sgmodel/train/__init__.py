"""Training, from batches to checkpoints: the ``sgmodel train`` command (``command``), the loop (``loop``), one
step (``step``), the objective (``losses``), several processes (``distributed``) and the encoder cache's command
(``encode_cache``).

Public names: ``loop.train``, ``step.train_step``, ``step.TrainingDiverged``.
"""
