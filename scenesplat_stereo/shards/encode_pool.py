"""Encoder workers: ``SampleEncoder`` (``encode.encode_sample`` in threads or processes behind a bounded queue,
and an in-order writer thread), and the encoder *processes* of its ``mode="processes"``.

Encoder threads share one GIL: every OpenImageIO call (spec, open, write, close) and every scratch-file
step takes it back, and a thread waiting for it behind a busy Python thread (the renderer's loop, the shard
writer, another encoder between two calls) waits up to ``sys.getswitchinterval()`` (5 ms) each time.
Measured on a 2-core CPU: a 616x456 JPEG that takes 0.95 ms alone took 3.5 ms in a thread beside one
pure-Python thread. Encoder processes do not share it; ``python -m scenesplat_stereo.bench.encode``
compares the two modes on the machine at hand.

Each process is started once per worker count and process (``spawn``: safe after CUDA or Warp have
started; it imports numpy and OpenImageIO only) and serves every ``SampleEncoder`` of that process.
Like any ``spawn`` start, a script that builds in this mode needs the ``if __name__ == "__main__":``
guard (the console scripts and ``python -m`` entries have it).
Images reach a worker through a ``common.scratch.Slot``: a file in the process's scratch folder (``/dev/shm``
when it has room), mapped in both processes, into which the calling thread copies a sample (one
``memcpy`` per array, no pickling); only the slot's name and the arrays' layout cross the pipe, and the
encoded bytes come back through it. Each worker sets OpenImageIO's ``threads`` to 1 (the workers are the
parallelism).
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from scenesplat_stereo.common.scratch import Layout, Slot, arrays_in
from scenesplat_stereo.shards import encode
from scenesplat_stereo.shards.sample import JPEG_QUALITY

ENCODER_MODES = ("auto", "threads", "processes")

_pools: dict[int, ProcessPoolExecutor] = {}
_pools_lock = threading.Lock()
_free_slots: list[Slot] = []  # slots of finished encoders, kept mapped here and in the workers
_slots_lock = threading.Lock()


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

    from scenesplat_stereo.common.commandline import quiet_worker_interrupts

    quiet_worker_interrupts()  # Ctrl-C: the command says one line; the workers nothing

    oiio.attribute("threads", 1)


def take_slots(n: int) -> list[Slot]:
    """``n`` slots, reused from finished encoders where possible (their pages are already allocated and
    mapped in the workers: a new 1752x1168 slot costs about 70 ms of page faults on first use)."""
    with _slots_lock:
        reused = [_free_slots.pop() for _ in range(min(n, len(_free_slots)))]
    return reused + [Slot() for _ in range(n - len(reused))]


def give_back_slots(slots: list[Slot]) -> None:
    """Return slots for the next encoder (the scratch folder and its files go at exit)."""
    with _slots_lock:
        _free_slots.extend(slots)


def encode_in_worker(path: str, layout: Layout, key: str, target_ids: tuple[int, ...], meta: bytes,
                     quality: int) -> dict[str, bytes]:
    """In a worker: the members of the sample whose arrays ``Slot.put`` copied to ``path`` under the names
    of ``SampleImages``' fields (``masks``; ``left``, ``right``, ``targets`` unless the caller holds the
    JPEGs already: then only ``encode_other_members``; ``depth`` when there is one)."""
    arrays = arrays_in(path, layout)
    sample = encode.SampleImages(key, arrays.get("left"), arrays.get("right"), arrays.get("targets"),
                                 arrays["masks"], target_ids, meta, arrays.get("depth"))
    try:
        if sample.left is not None:
            return encode.encode_sample(sample, quality)
        return encode.encode_other_members(sample)
    finally:
        del sample, arrays  # no view may outlive the call: the mapping can be closed on the next miss


def default_encoder_workers() -> int:
    """Encoder workers by default: half the CPU cores (at least 1). Measured on a 16-core GPU host
    (docs/benchmarks.md, bench build): JPEG throughput peaks at 8 threads and falls at 16, where the
    encoders compete with the renderer's own thread and OpenImageIO's I/O for the cores."""
    return max(1, (os.cpu_count() or 1) // 2)


#: "auto" picks encoder processes on a machine with at least this many cores, else threads. Measured
#: (docs/benchmarks.md, issue 12): on the 16-core H100 host the build ran 139 pairs/s with 8 encoder
#: processes against 73 with 8 threads at 616x456 (threads wait for the GIL behind the renderer's Python
#: thread), 25 against 28 at 1752x1168; on the 2-core development machine threads win (72.7 against 70.5
#: samples/s at 616x456, 13.5 against 9.1 at 1752x1168): there the extra processes compete for two cores.
PROCESSES_MIN_CORES = 8
DEFAULT_ENCODER_MODE = "auto"


def resolve_encoder_mode(mode: str) -> str:
    """"threads" or "processes" for ``mode`` ("auto": processes on PROCESSES_MIN_CORES cores or more)."""
    if mode not in ENCODER_MODES:
        raise ValueError(f"encoder mode must be one of {ENCODER_MODES}, got {mode!r}")
    if mode == "auto":
        return "processes" if (os.cpu_count() or 1) >= PROCESSES_MIN_CORES else "threads"
    return mode


class SampleEncoder:
    """Encoder workers behind a bounded queue, and one writer thread that hands the results to
    ``sink(key, members)`` in submission order.

    ``mode`` "threads": ``workers`` threads encode. "processes": ``workers`` threads each copy a sample
    into a shared slot and wait while one of ``workers`` encoder processes (started once
    per process and reused) encodes it; the bytes are the same. ``workers=0`` encodes and writes inline
    (no threads, no processes), whatever the mode.

    The renderer calls ``submit`` and goes back to rendering: it blocks only while ``max_pending``
    samples are queued (encoding, or encoded and waiting for the writer). Writing (tar, checksum) runs in
    the writer thread, one sample at a time, in order, whatever the encoder timing. An error in encoding
    (in a thread or a process) or in the sink stops the writer and is raised by the next ``submit`` or by
    ``close``. ``close`` (or leaving the ``with`` block normally) drains the queue; leaving it with an
    exception drops the queued samples without handing them to the sink.

    Timings (seconds): ``encode_s`` summed over encoder threads (processes mode: copy to the slot, the
    worker's encoding and the bytes' way back), ``wait_s`` the caller's time blocked on the queue,
    ``sink_s`` time spent in the sink.
    """

    def __init__(
        self,
        sink: Callable[[str, dict[str, bytes]], None],
        workers: int,
        quality: int = JPEG_QUALITY,
        max_pending: int | None = None,
        mode: str = DEFAULT_ENCODER_MODE,
    ) -> None:
        if workers < 0:
            raise ValueError(f"SampleEncoder: workers must be >= 0, got {workers}")
        mode = resolve_encoder_mode(mode)
        self.sink, self.quality, self.workers = sink, quality, workers
        self.max_pending = max_pending if max_pending is not None else max(2, 3 * workers)
        self.encode_s = self.wait_s = self.sink_s = 0.0
        self._time_lock = threading.Lock()
        self._error: BaseException | None = None
        self._stop = threading.Event()
        self._procs = process_pool(workers) if workers and mode == "processes" else None
        # one slot per thread: a free slot is always there for a running thread
        self._all_slots = take_slots(workers) if self._procs is not None else []
        self._slots: queue.SimpleQueue = queue.SimpleQueue()
        for slot in self._all_slots:
            self._slots.put(slot)
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="encode") if workers else None
        self._queue: queue.Queue = queue.Queue(maxsize=self.max_pending)
        self._writer = None
        if self._pool is not None:
            self._writer = threading.Thread(target=self._write_loop, name="shard-writer", daemon=True)
            self._writer.start()

    def _encode(self, sample: encode.SampleImages) -> dict[str, bytes]:
        t0 = time.perf_counter()
        if self._procs is None:
            members = encode.encode_sample(sample, self.quality)
        else:
            members = self._encode_in_process(sample)
        with self._time_lock:
            self.encode_s += time.perf_counter() - t0
        return members

    def _encode_in_process(self, sample: encode.SampleImages) -> dict[str, bytes]:
        slot = self._slots.get()
        try:
            names = ("masks", "depth") + (() if sample.jpegs is not None else ("left", "right", "targets"))
            arrays = {n: getattr(sample, n) for n in names if getattr(sample, n) is not None}
            path, layout = slot.put(arrays)
            future = self._procs.submit(encode_in_worker, path, layout, sample.key,
                                        tuple(sample.target_ids), sample.meta, self.quality)
            try:
                return (sample.jpegs or {}) | future.result()
            except BrokenProcessPool:
                discard_pool(self.workers, self._procs)
                raise
        finally:
            self._slots.put(slot)

    def _write(self, key: str, members: dict[str, bytes]) -> None:
        t0 = time.perf_counter()
        self.sink(key, members)
        self.sink_s += time.perf_counter() - t0

    def _write_loop(self) -> None:
        while (item := self._queue.get()) is not None:
            if self._error is not None or self._stop.is_set():
                continue  # keep draining so that the producer never blocks on a dead writer
            try:
                self._write(item[0], item[1].result())
            except BaseException as e:  # noqa: BLE001  (handed to the producer thread, re-raised there)
                self._error = e

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise self._error

    def submit(self, sample: encode.SampleImages) -> None:
        """Queue one sample; blocks while ``max_pending`` samples are queued."""
        self._raise_if_failed()
        t0 = time.perf_counter()
        if self._pool is None:
            members = self._encode(sample)
            self.wait_s += time.perf_counter() - t0
            self._write(sample.key, members)
            return
        self._queue.put((sample.key, self._pool.submit(self._encode, sample)))
        self.wait_s += time.perf_counter() - t0

    def close(self) -> None:
        """Wait until every queued sample has been handed to the sink, in order; raise a pending error."""
        self._finish()
        self._raise_if_failed()

    def abort(self) -> None:
        """Drop the queued samples (their results never reach the sink)."""
        self._stop.set()
        self._finish()

    def _finish(self) -> None:
        if self._writer is not None and self._writer.is_alive():
            self._queue.put(None)
            self._writer.join()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        give_back_slots(self._all_slots)
        self._all_slots = []

    def __enter__(self) -> SampleEncoder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
