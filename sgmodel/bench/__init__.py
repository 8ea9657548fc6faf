"""Model benchmarks (``sgmodel bench ...``), each a module with ``add_arguments(parser)`` and ``run(args)``
that prints a markdown table: ``train`` (one training step split by stage, peak memory), ``encoders``
(each encoder's time per pair and disparity error against rendered depth) and ``predict`` (one pair to a
scene in a warm process, split by stage)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import torch

from scenesplat_stereo.files import atomic_write_bytes


def synced_clock(device: torch.device) -> Callable[[], float]:
    """A clock (seconds) that first waits for ``device``'s queued work, so that stage times are honest."""
    def now() -> float:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return time.perf_counter()
    return now


def report(text: str, out: Path | None) -> None:
    """Print a benchmark's markdown and, with ``--out``, write it there too (atomically)."""
    print(text)
    if out:
        atomic_write_bytes(Path(out), text.encode())
