"""Model benchmarks (``sgmodel bench ...``), each a module with ``add_arguments(parser)`` and ``run(args)``
that prints a markdown table: ``train`` (one training step split by stage, peak memory) and ``encoders``
(each encoder's time per pair and disparity error against rendered depth)."""
