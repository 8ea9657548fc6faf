"""Row-range tasks on one shared thread pool, for the scene writers' quantisation (``spz``, ``compressed_ply``;
``sog`` runs its texels, SH palette and WebP encodes there as tasks of their own), and the device of the
writers' torch work (the Morton order, ``sog_texels``).

A writer splits its N rows into slices of ``ROWS_PER_TASK`` (a multiple of the compressed ``.ply``'s 256-row
chunk) and quantises each slice in a task that writes its own rows of preallocated output arrays, so the
result does not depend on how the rows were split or in which order the tasks ran. numpy releases the GIL
inside its array loops, so the slices run on the host's cores side by side; between two numpy calls a task
holds the GIL, so a slice is large enough for each call's loop to outweigh that (32,768 rows: on 2 cores the
compressed ``.ply`` of 202,752 Gaussians is about a fifth faster than with slices of 8,192; docs/benchmarks.md
"Scene writers") and small enough that a slice's float64 temporaries (32,768 rows x 24 SH coefficients: 6 MB)
stay in the CPU's last-level cache.

The pool is created on first use with ``workers()`` threads and shared by every writer in the process; a forked
child makes its own. A process that writes beside others (``sgmodel predict --video --frames``' writer processes,
``sgmodel.predict.scene_writers``) pins its thread count (and the CPU) with ``pin`` before its first write. A task
must never wait for another task of this pool (that could deadlock a full pool); writers wait in their own thread.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

#: Rows per task (a multiple of 256, the compressed .ply's chunk).
ROWS_PER_TASK = 32768
#: Threads of the shared pool at most.
MAX_WORKERS = 16

_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()
#: ``pin``'s threads (None: ``workers()``'s and ``device()``'s defaults).
_pinned: int | None = None


def _forget_pool() -> None:
    """In a forked child the parent's pool threads do not exist: the child makes its own on first use."""
    global _pool, _lock
    _pool, _lock = None, threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def pin(threads: int) -> None:
    """Set this process's pool to ``threads`` threads and its writers' torch work to the CPU (a writer process
    beside a model on the GPU); before the pool's first use."""
    global _pinned
    with _lock:
        if _pool is not None:
            raise RuntimeError("row_tasks.pin: the pool is already in use")
        _pinned = max(1, int(threads))


def workers() -> int:
    """Threads of the shared pool: ``pin``'s, else the CPUs this process may run on, at most ``MAX_WORKERS``."""
    if _pinned is not None:
        return _pinned
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(MAX_WORKERS, cpus))


def pool() -> ThreadPoolExecutor:
    """The shared pool (created on first use)."""
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(workers(), thread_name_prefix="row-tasks")
        return _pool


def row_ranges(n: int, step: int | None = None) -> list[tuple[int, int]]:
    """[(start, end), ...] covering rows 0..n in slices of ``step`` (default ``ROWS_PER_TASK``, read at each
    call; the last slice shorter)."""
    step = step or ROWS_PER_TASK
    return [(a, min(a + step, n)) for a in range(0, n, step)]


def submit_rows(fn: Callable[[int, int], object], n: int, step: int | None = None) -> list[Future]:
    """``fn(start, end)`` for every slice of ``row_ranges(n, step)``, queued on the shared pool in order."""
    p = pool()
    return [p.submit(fn, a, b) for a, b in row_ranges(n, step)]


def wait_all(futures: list[Future]) -> None:
    """Wait for every future; the first exception (in submission order) is raised once all have ended, so no
    task still writes into a caller's arrays after the caller has moved on."""
    error = None
    for f in futures:
        try:
            f.result()
        except BaseException as e:  # noqa: BLE001 - re-raised below, after the others ended
            error = error or e
    if error is not None:
        raise error


def device() -> torch.device:
    """Where the writers' torch work runs: the current CUDA device when there is one and ``pin`` was not called, else
    the CPU."""
    import torch  # only for writing: the readers do without it

    if _pinned is not None:
        return torch.device("cpu")
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
