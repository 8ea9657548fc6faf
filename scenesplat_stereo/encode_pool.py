"""Encoder *processes* for ``SampleEncoder(mode="processes")``: the same ``encode_sample``, run outside the
caller's GIL.

Encoder threads share one GIL: every OpenImageIO call (spec, open, write, close) and every scratch-file
step takes it back, and a thread waiting for it behind a busy Python thread (the renderer's loop, the shard
writer, another encoder between two calls) waits up to ``sys.getswitchinterval()`` (5 ms) each time.
Measured on a 2-core CPU: a 616x456 JPEG that takes 0.95 ms alone took 3.5 ms in a thread beside one
pure-Python thread. Encoder processes do not share it.

Each process is started once per worker count and process (``spawn``: safe after CUDA or Warp have
started; it imports numpy and OpenImageIO only) and serves every ``SampleEncoder`` of that process.
Like any ``spawn`` start, a script that builds in this mode needs the ``if __name__ == "__main__":``
guard (the console scripts and ``python -m`` entries have it).
Images reach a worker through a ``Slot``: a file in the encoder's private scratch folder (``/dev/shm``
when it has room), mapped in both processes, into which the calling thread copies a sample (one
``memcpy`` per array, no pickling); only the slot's name and the arrays' layout cross the pipe, and the
encoded bytes come back through it. Each worker sets OpenImageIO's ``threads`` to 1 (the workers are the
parallelism).
"""

from __future__ import annotations

import itertools
import mmap
import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor

import numpy as np

_ALIGN = 64  # bytes; each array in a slot starts on a cache line
_pools: dict[int, ProcessPoolExecutor] = {}
_pools_lock = threading.Lock()
_slot_ids = itertools.count()
_maps: dict[str, mmap.mmap] = {}  # in a worker: slot path -> its mapping
_free_slots: list[Slot] = []  # slots of finished encoders, kept mapped here and in the workers
_slots_lock = threading.Lock()

# (name, offset in bytes, shape, dtype string) of each array in a slot
Layout = list[tuple[str, int, tuple[int, ...], str]]


def process_pool(workers: int) -> ProcessPoolExecutor:
    """This process's pool of ``workers`` encoder processes (started on first use, reused after)."""
    with _pools_lock:
        pool = _pools.get(workers)
        if pool is None:
            ctx = multiprocessing.get_context("spawn")
            pool = _pools[workers] = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker)
        return pool


def discard_pool(workers: int, pool: ProcessPoolExecutor) -> None:
    """Forget a broken pool (a worker died) so that the next ``process_pool`` starts a new one."""
    with _pools_lock:
        if _pools.get(workers) is pool:
            del _pools[workers]
    pool.shutdown(wait=False, cancel_futures=True)


def start_workers(workers: int) -> None:
    """Start all ``workers`` processes now (a pool starts them one task at a time otherwise)."""
    pool = process_pool(workers)
    for f in [pool.submit(_ping, 0.05) for _ in range(workers)]:
        f.result()


def _ping(seconds: float) -> int:
    import time

    time.sleep(seconds)
    return os.getpid()


def _init_worker() -> None:
    import OpenImageIO as oiio

    oiio.attribute("threads", 1)


def take_slots(n: int, folder: str) -> list[Slot]:
    """``n`` slots, reused from finished encoders where possible (their pages are already allocated and
    mapped in the workers: a new 1752x1168 slot costs about 70 ms of page faults on first use)."""
    with _slots_lock:
        reused = [_free_slots.pop() for _ in range(min(n, len(_free_slots)))]
    return reused + [Slot(folder) for _ in range(n - len(reused))]


def give_back_slots(slots: list[Slot]) -> None:
    """Return slots for the next encoder (the scratch folder and its files go at exit)."""
    with _slots_lock:
        _free_slots.extend(slots)


class Slot:
    """A shared buffer for one sample at a time: a file in ``folder`` mapped here (grown as needed) and,
    by path, in the workers. The calling thread owns it from ``put`` until the worker's result is back."""

    def __init__(self, folder: str) -> None:
        self.folder, self.path, self.buf = folder, "", None

    def put(self, arrays: dict[str, np.ndarray]) -> tuple[str, Layout]:
        """Copy named ``arrays`` into the slot; returns (path, layout) for ``encode_in_worker``."""
        layout, offset = [], 0
        for name, a in arrays.items():
            layout.append((name, offset, tuple(a.shape), a.dtype.str))
            offset += -(-a.nbytes // _ALIGN) * _ALIGN
        if self.buf is None or len(self.buf) < offset:
            self._grow(offset)
        for (name, off, shape, dtype) in layout:
            np.copyto(np.ndarray(shape, dtype, buffer=self.buf, offset=off), arrays[name], casting="no")
        return self.path, layout

    def _grow(self, nbytes: int) -> None:
        self.close()  # a new file (a new name): workers map it afresh and drop the old one
        self.path = os.path.join(self.folder, f"slot-{os.getpid()}-{next(_slot_ids)}")
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.ftruncate(fd, nbytes)
            self.buf = mmap.mmap(fd, nbytes)
        finally:
            os.close(fd)

    def close(self) -> None:
        if self.buf is not None:
            self.buf.close()
            self.buf = None
        if self.path:
            try:
                os.remove(self.path)
            except FileNotFoundError:
                pass
            self.path = ""


def _mapping(path: str) -> mmap.mmap:
    """The worker's mapping of a slot file; mappings of removed slot files are dropped on a miss."""
    buf = _maps.get(path)
    if buf is None:
        for old in [p for p in _maps if not os.path.exists(p)]:
            _maps.pop(old).close()
        with open(path, "r+b") as f:
            buf = _maps[path] = mmap.mmap(f.fileno(), 0)
    return buf


def encode_in_worker(path: str, layout: Layout, key: str, target_ids: tuple[int, ...], meta: bytes,
                     quality: int) -> dict[str, bytes]:
    """In a worker: the members of the sample whose arrays ``Slot.put`` copied to ``path`` under the names
    of ``SampleImages``' fields (``masks``; ``left``, ``right``, ``targets`` unless the caller holds the
    JPEGs already: then only ``encode_other_members``; ``depth`` when there is one)."""
    from scenesplat_stereo.encode import SampleImages, encode_other_members, encode_sample

    buf = _mapping(path)
    arrays = {name: np.ndarray(shape, dtype, buffer=buf, offset=off) for name, off, shape, dtype in layout}
    sample = SampleImages(key, arrays.get("left"), arrays.get("right"), arrays.get("targets"), arrays["masks"],
                          target_ids, meta, arrays.get("depth"))
    try:
        return encode_sample(sample, quality) if sample.left is not None else encode_other_members(sample)
    finally:
        del sample, arrays  # no view may outlive the call: the mapping can be closed on the next miss
