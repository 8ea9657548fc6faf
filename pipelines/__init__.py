"""Dataset pipelines run from a source checkout: ``python -m pipelines.irs_pose_recovery``,
``python -m pipelines.irs_targets`` (IRS, paper appendix F; see docs/irs.md)."""
