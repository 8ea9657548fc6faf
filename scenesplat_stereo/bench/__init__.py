"""Benchmarks (``scenesplat-stereo bench ...``), each a module with ``add_arguments(parser)`` and ``run(args)``
that prints markdown tables: ``render`` (the rasteriser's accuracy knobs against time), ``build`` (the
dataset build's throughput and the projected time of the paper's full dataset) and ``scenes`` (every scene
writer's time and file size)."""
