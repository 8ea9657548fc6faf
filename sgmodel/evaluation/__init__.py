"""Judging methods as the paper does: ``sgmodel eval`` (``command``), one method on one split (``evaluate``),
the Table 2 layout for several (``table2``) and the Table 4 ablation (``ablate``, the ``sgmodel ablate`` command).

Public names: ``evaluate.evaluate``, ``ablate.ablate``, ``table2.run_table``.
"""
