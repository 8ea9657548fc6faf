"""Writing predicted scenes: ``write_scene`` (one file, as ``sgmodel predict`` writes it) and ``SceneWriters``, the
processes that write a scene per frame beside the model (``sgmodel predict --video --frames``).

Why processes. A compact writer (SOG, ``.spz``, compressed ``.ply``) is numpy and torch calls with Python between
them, and on a GPU host its torch work is kernel launches: in threads of the model's process a dozen of them
hold the GIL and the CUDA driver against each other and against the model's own launches, and wrote 12-20
scenes a second at 448x256 where the model makes 80 (docs/benchmarks.md "Issue 35: the SOG writer's encodes
queued as their texels are ready"). Each ``SceneWriters`` process has an interpreter of its own:

* A scene reaches a process through a ``common.scratch.Slot`` (a file in RAM both map: one copy of its arrays,
  14 float32 a Gaussian at SH degree 0, 38 at degree 2), not pickled through the pool's pipe: that way 12
  processes wrote 15 scenes a second at 448x256 whatever the format, ``.ply`` included (docs/benchmarks.md).
  The file is the one ``write_scene`` writes in the parent, byte for byte.
* The processes are spawned (a parent holding a CUDA context cannot fork), started together and waited for
  when the pool is made, so the first frames do not wait for the imports. Each pins the writers' shared row
  pool to ``threads`` threads and their torch work to the CPU (``row_tasks.pin``): the processes stay off the GPU
  the model runs on (a CUDA context in each was no faster and costs GPU memory: docs/benchmarks.md).
* Errors come back through each write's future as the writer raised them (a bad scene's ``ValueError`` stays
  exit 2 on the command line); a process that dies breaks the pool (``BrokenProcessPool``, a ``RuntimeError``).
  On Ctrl-C the processes end silently (``quiet_worker_interrupts``) and the command says its one line.
"""

from __future__ import annotations

import multiprocessing
import queue
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from scenesplat_stereo.common.commandline import quiet_worker_interrupts
from scenesplat_stereo.common.scratch import Layout, Slot, arrays_in
from scenesplat_stereo.scene import row_tasks
from scenesplat_stereo.scene.gaussians import GaussianScene
from scenesplat_stereo.scene.scene_files import save_scene

#: Seconds the processes may take to start (spawn, then numpy, torch and OpenImageIO imported in each).
START_TIMEOUT = 120.0
#: The arrays of a ``GaussianScene``.
FIELDS = ("means", "quats", "scales", "opacities", "sh")


def write_scene(scene: GaussianScene, path: str | Path, format: str = "ply") -> Path:
    """Write ``scene`` in a ``scene_files.FORMATS`` format (atomically, without fsync: a prediction is cheap to
    make again and the fsync would cost more than the rest of the write, docs/benchmarks.md)."""
    return save_scene(scene, path, format, durable=False)


_started = None  # in a writer process: the barrier of ``SceneWriters``' start


def _start(threads: int, started) -> None:
    """A writer process's initialiser: Ctrl-C left to the parent, torch imported, the row pool pinned."""
    global _started
    quiet_worker_interrupts()
    import torch  # imported here, not by the first write

    torch.set_num_threads(threads)
    row_tasks.pin(threads)
    _started = started


def _write_slot(slot: str, layout: Layout, sh_degree: int, path: Path, format: str, write) -> tuple[Path, float]:
    """In a writer process: ``write`` the scene whose arrays ``SceneWriters.write`` put in ``slot`` to ``path``;
    (the path, the seconds it took)."""
    start = time.perf_counter()
    path = write(GaussianScene(**arrays_in(slot, layout), sh_degree=sh_degree), path, format)
    return path, time.perf_counter() - start


def _ready() -> None:
    """The first task of each writer process: wait until every process has one (so each has started)."""
    _started.wait(START_TIMEOUT)


class SceneWriters:
    """``processes`` writer processes (module docstring), each with ``threads`` threads (default: this process's
    usable CPUs shared out, at least 1) for its torch work. ``busy_s``: the seconds they have spent
    writing, summed (busy_s / (processes x wall time) near 1: the writers are what holds a stream back)."""

    def __init__(self, processes: int, threads: int | None = None) -> None:
        context = multiprocessing.get_context("spawn")
        self.processes = max(1, processes)
        self.busy_s, self._lock = 0.0, threading.Lock()  # seconds the processes spent writing, summed
        self.slots: queue.SimpleQueue[Slot] = queue.SimpleQueue()
        for _ in range(self.processes):
            self.slots.put(Slot())
        threads = threads or max(1, row_tasks.workers() // self.processes)
        started = context.Barrier(self.processes + 1)
        self.pool = ProcessPoolExecutor(self.processes, mp_context=context, initializer=_start,
                                        initargs=(threads, started))
        try:  # the pool spawns a process for each task that finds none idle
            ready = [self.pool.submit(_ready) for _ in range(self.processes)]
            started.wait(START_TIMEOUT)
            for f in ready:
                f.result()
        except BaseException:
            self.pool.shutdown(wait=False, cancel_futures=True)
            self._close_slots()
            raise

    def write(self, scene: GaussianScene, path: Path, format: str, write=write_scene) -> Path:
        """``write(scene, path, format)`` (``write_scene``, or another module-level function of that signature) in
        a writer process; returns the path written. Blocks while every slot is in use (one per process)."""
        slot = self.slots.get()
        try:
            where, layout = slot.put({name: getattr(scene, name) for name in FIELDS})
            path, seconds = self.pool.submit(_write_slot, where, layout, scene.sh_degree, path, format, write).result()
        finally:
            self.slots.put(slot)
        with self._lock:
            self.busy_s += seconds
        return path

    def close(self, cancel: bool = False) -> None:
        """Wait for the queued writes (``cancel``: only for those already started), then end the processes and
        remove the slots."""
        self.pool.shutdown(wait=True, cancel_futures=cancel)
        self._close_slots()

    def _close_slots(self) -> None:
        while not self.slots.empty():
            self.slots.get().close()
