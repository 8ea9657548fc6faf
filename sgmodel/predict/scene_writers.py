"""Writing predicted scenes: ``write_scene`` (one file, as ``sgmodel predict`` writes it) and ``SceneWriters``, the
processes that write a scene per frame beside the model (``sgmodel predict --video --frames``).

Why processes. A compact writer (SOG, ``.spz``, compressed ``.ply``) is numpy and torch calls with Python between
them, and on a GPU host its torch work is kernel launches: in threads of the model's process a dozen of them
hold the GIL and the CUDA driver against each other and against the model's own launches, and wrote 12-20
scenes a second at 448x256 where the model makes 80 (docs/benchmarks.md "Issue 35: the SOG writer's encodes
queued as their texels are ready"). Each ``SceneWriters`` process has an interpreter of its own:

* Each process has a pipe and a ``common.scratch.Slot`` of its own (a file in RAM both map), and serves one
  calling thread at a time: the thread copies the scene's arrays into the slot (14 float32 a Gaussian at SH degree
  0, 38 at degree 2), sends their layout and waits for the answer. Pickled through a pool's pipe instead, 12
  processes wrote 15 scenes a second at 448x256 whatever the format, ``.ply`` included (docs/benchmarks.md).
  The file is the one ``write_scene`` writes in the parent, byte for byte.
* The processes are spawned (a parent holding a CUDA context cannot fork), started together and waited for
  when ``SceneWriters`` is made, so the first frames do not wait for the imports. Each pins the writers' shared row
  pool to ``threads`` threads and their torch work to the CPU (``row_tasks.pin``): the processes stay off the GPU
  the model runs on (a CUDA context in each was no faster and costs GPU memory: docs/benchmarks.md).
* A SOG's quantisation (``QUANTISED_ON_DEVICE``) runs in the calling thread when the model is on a GPU
  (``write``'s ``dev``): there its torch work takes milliseconds; on a writer process's CPU it took 3.5 s of CPU
  for 202,752 Gaussians at SH 2, mostly the SH palette's k-means (``sgmodel bench predict`` on a 2-core machine).
  The process gets the texels and encodes them (``SceneWriters.run``).
* Errors come back as the writer raised them (a bad scene's ``ValueError`` stays exit 2 on the command line); a
  process that dies is ``BrokenProcessPool`` (a ``RuntimeError``: exit 1) in the thread that waited for it.
  On Ctrl-C the processes end silently (``quiet_worker_interrupts``) and the command says its one line.
"""

from __future__ import annotations

import multiprocessing
import queue
import threading
import time
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.common.commandline import quiet_worker_interrupts
from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.common.scratch import Slot, arrays_in
from scenesplat_stereo.scene import row_tasks
from scenesplat_stereo.scene.gaussians import ARRAYS, GaussianScene
from scenesplat_stereo.scene.scene_files import save_scene
from scenesplat_stereo.scene.sog import IMAGES, SogImage, encode_images, quantise_sog

#: Seconds the processes may take to start (spawn, then numpy, torch and OpenImageIO imported in each).
START_TIMEOUT = 120.0


def write_scene(scene: GaussianScene, path: str | Path, format: str = "ply") -> Path:
    """Write ``scene`` in a ``scene_files.FORMATS`` format (atomically, without fsync: a prediction is cheap to
    make again and the fsync would cost more than the rest of the write, docs/benchmarks.md)."""
    return save_scene(scene, path, format, durable=False)


def _serve(connection, threads: int) -> None:
    """A writer process: Ctrl-C left to the parent, torch imported, the row pool pinned, then "ready"; then each
    message (slot, layout, function, path, arguments) answered with (True, (function(arrays in the slot, path,
    *arguments), seconds)) or (False, the error), until None."""
    quiet_worker_interrupts()
    import torch  # imported here, not by the first write

    torch.set_num_threads(threads)
    row_tasks.pin(threads)
    connection.send("ready")
    while (message := connection.recv()) is not None:
        slot, layout, function, path, args = message
        start = time.perf_counter()
        try:
            answer = (True, (function(arrays_in(slot, layout), path, *args), time.perf_counter() - start))
        except Exception as e:  # noqa: BLE001 - raised again in the parent
            answer = (False, e)
        try:
            connection.send(answer)
        except Exception as e:  # noqa: BLE001 - an error that cannot be pickled: its text
            connection.send((False, RuntimeError(f"{type(e).__name__} in a scene writer process: {e}")))


def _scene_file(arrays: dict[str, np.ndarray], path: Path, sh_degree: int, format: str, write) -> Path:
    """In a writer process: ``write`` the scene of ``arrays`` (``gaussians.ARRAYS``)."""
    return write(GaussianScene(**arrays, sh_degree=sh_degree), path, format)


def _sog_parts(scene: GaussianScene, path: Path, dev: torch.device) -> tuple[dict[str, np.ndarray], tuple]:
    """In the model's process: the SOG's quantisation on ``dev`` (``sog.quantise_sog``) as (the images' texels and
    the Morton order, (the images' sizes and methods, meta.json)) for ``_sog_file``."""
    images: dict[str, SogImage] = {}
    meta = quantise_sog(scene, images.__setitem__, path, dev=dev)
    arrays = {name: image.texels for name, image in images.items()}
    arrays["order"] = images[IMAGES[0]].order
    return arrays, ({name: (i.width, i.height, i.method, i.order is not None) for name, i in images.items()}, meta)


def _sog_file(arrays: dict[str, np.ndarray], path: Path, sizes: dict[str, tuple[int, int, int, bool]],
              meta: dict) -> Path:
    """In a writer process: the SOG of ``_sog_parts``' images, encoded and bundled (``sog.encode_images``),
    written as ``write_scene`` writes it."""
    images = {name: SogImage(arrays[name], w, h, method, arrays["order"] if ordered else None)
              for name, (w, h, method, ordered) in sizes.items()}
    atomic_write_bytes(path, encode_images(images, meta), durable=False)
    return path


#: Formats whose quantisation runs in the model's process, on its GPU (``SceneWriters.write``'s ``dev``), and the
#: rest in a writer process: (the quantisation, the rest). A SOG's torch work (the Morton order, the codebooks and
#: the SH palette's k-means) is milliseconds there (module docstring).
QUANTISED_ON_DEVICE = {"sog": (_sog_parts, _sog_file)}


@dataclass
class _Writer:
    """One writer process, the parent's end of its pipe and the slot that carries its scenes."""

    process: multiprocessing.process.BaseProcess
    connection: Connection
    slot: Slot


class SceneWriters:
    """``processes`` writer processes (module docstring), each with ``threads`` threads (default: this process's
    usable CPUs shared out, at least 1) for its torch work. ``write`` may be called from that many threads at once;
    each call has a process (and its slot) to itself. ``busy_s``: the seconds the processes have spent writing,
    summed (busy_s / (processes x wall time) near 1: the writers are what holds a stream back)."""

    def __init__(self, processes: int, threads: int | None = None) -> None:
        context = multiprocessing.get_context("spawn")
        threads = threads or max(1, row_tasks.workers() // max(1, processes))
        self.busy_s, self._lock = 0.0, threading.Lock()
        self.writers: list[_Writer] = []
        self._idle: queue.SimpleQueue[_Writer] = queue.SimpleQueue()
        try:
            for i in range(max(1, processes)):
                parent, child = context.Pipe()
                process = context.Process(target=_serve, args=(child, threads), name=f"scene-writer-{i}", daemon=True)
                process.start()
                child.close()
                self.writers.append(_Writer(process, parent, Slot()))
            for w in self.writers:  # started together, waited for together
                if not w.connection.poll(START_TIMEOUT):
                    raise RuntimeError(f"{w.process.name} did not start in {START_TIMEOUT:.0f} s")
                self._answer(w, "starting")
        except BaseException:
            self.close()
            raise
        for w in self.writers:
            self._idle.put(w)

    def write(self, scene: GaussianScene, path: Path, format: str, write=write_scene,
              dev: torch.device | None = None) -> Path:
        """``write(scene, path, format)`` (``write_scene``, or another module-level function of that signature) in
        a writer process; returns the path written. With ``dev`` (a GPU), a format of ``QUANTISED_ON_DEVICE`` is
        quantised there in this thread first and only the rest runs in the process (the same bytes as
        ``write_scene`` on that device). Blocks while every process is busy."""
        if dev is not None and write is write_scene and format in QUANTISED_ON_DEVICE:
            quantise, finish = QUANTISED_ON_DEVICE[format]
            arrays, args = quantise(scene, path, dev)
            return self.run(finish, path, arrays, *args)
        return self.run(_scene_file, path, {name: getattr(scene, name) for name in ARRAYS}, scene.sh_degree, format,
                        write)

    def run(self, function, path: Path, arrays: dict[str, np.ndarray], *args) -> Path:
        """``function(arrays, path, *args)`` (module-level, returning the path it wrote) in a writer process,
        ``arrays`` carried by its slot and the rest pickled; returns that path."""
        w = self._idle.get()
        try:
            where, layout = w.slot.put(arrays)
            try:
                w.connection.send((where, layout, function, path, args))
            except OSError as e:  # the pipe is closed: the process has ended
                self._answer(w, f"writing {path}", e)
            ok, value = self._answer(w, f"writing {path}")
        finally:
            self._idle.put(w)
        if not ok:
            raise value
        path, seconds = value
        with self._lock:
            self.busy_s += seconds
        return path

    @staticmethod
    def _answer(w: _Writer, doing: str, error: BaseException | None = None) -> object:
        """The next message of ``w``'s process; ``BrokenProcessPool`` naming it when it has ended (or ``error``
        says so)."""
        try:
            if error is None:
                return w.connection.recv()
        except (EOFError, OSError) as e:
            error = e
        w.process.join(5.0)
        raise BrokenProcessPool(f"{w.process.name} ended (exit code {w.process.exitcode}) while {doing}") from error

    def close(self) -> None:
        """End the processes (after the writes they have begun) and remove the slots."""
        for w in self.writers:
            try:
                w.connection.send(None)
            except OSError:  # it has ended already
                pass
        for w in self.writers:
            w.process.join(START_TIMEOUT)
            if w.process.is_alive():
                w.process.kill()
            w.connection.close()
            w.slot.close()
