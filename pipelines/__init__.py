"""Dataset pipelines (IRS, paper appendix F; see docs/irs.md), installed as the commands ``irs-pose-recovery``
and ``irs-targets``; ``python pipelines/<tool>.py`` and ``python -m pipelines.<tool>`` run the same."""
