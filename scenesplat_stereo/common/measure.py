"""What benchmarks and metrics measure with, in one place for both packages: a clock that waits for the
device's queued work (seconds), the median of repeated timed runs, and the PSNR formula (dB).

Every benchmark, ``sgmodel predict``'s stage log and the video pipeline take their times from
``synced_clock``; every PSNR in the project (``sgmodel.metrics.image.psnr`` over masked, clipped images,
the rasteriser benchmark against the float64 reference, the JPEG check of the build benchmark) ends in
``psnr_from_mse``.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable

import torch


def synchronize(device: str | torch.device) -> None:
    """Wait for the work queued on ``device`` (a CUDA device; nothing to wait for on the CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def synced_clock(device: str | torch.device) -> Callable[[], float]:
    """A clock (seconds) that first waits for ``device``'s queued work, so that stage times are honest."""
    def now() -> float:
        synchronize(device)
        return time.perf_counter()
    return now


def median_seconds(fn: Callable[[], object], device: str | torch.device, repeats: int, warmup: int = 2) -> float:
    """Median wall time (seconds) of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones, each call
    timed to the end of its device work."""
    for _ in range(warmup):
        fn()
    now = synced_clock(device)
    times = []
    for _ in range(repeats):
        t0 = now()
        fn()
        times.append(now() - t0)
    return statistics.median(times)


def psnr_from_mse(mse, peak: float = 1.0):
    """PSNR in dB of a mean squared error for signals of range ``peak`` (a float, or a tensor of them);
    +inf for a float mse of 0."""
    if isinstance(mse, torch.Tensor):
        return 10 * torch.log10(peak ** 2 / mse)
    return float("inf") if mse == 0 else 10 * math.log10(peak ** 2 / mse)
