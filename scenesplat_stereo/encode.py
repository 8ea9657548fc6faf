"""Encoding rendered images to the bytes stored in shards (SPEC sections 4 and 5), through OpenImageIO.

- Colour images: 8-bit sRGB-as-rendered JPEG, quality ``JPEG_QUALITY`` (92, paper appendix B), 4:2:0
  chroma subsampling, baseline (non-progressive) coding.
- Valid masks: 8-bit single-channel PNG holding 0 or 255 (rendered alpha >= 0.5 -> 255), written with zlib.
- Left depth (``--with-depth``): single-channel float16 OpenEXR (ZIP), expected depth along the camera's
  z axis in world units (metres); 0 where nothing was rendered.

Every encoder fixes all settings (and the EXR ``DateTime``, which OpenImageIO otherwise stamps with the
wall clock), so the same pixels always give the same bytes. OpenImageIO's Python bindings cannot write to
memory, so each call goes through a per-thread scratch file in a private folder (in ``/dev/shm`` when it
has 1 GiB free, else the system temp folder), read back and removed.

``SampleEncoder`` keeps the renderer from waiting on the encoder: a bounded queue of samples encoded by
worker threads, or by worker processes that those threads feed (``encode_pool``: the same bytes, outside
the caller's GIL), and a writer thread that hands them, in submission order, to the shard writer.
OpenImageIO releases the GIL while it encodes, but every call takes it back, and with a busy Python
thread beside them encoder threads wait for it (``encode_pool`` has the measurement); ``python -m
scenesplat_stereo.bench.encode`` compares the two modes on the machine at hand.
"""

from __future__ import annotations

import atexit
import os
import queue
import shutil
import struct
import tempfile
import threading
import time
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np
import OpenImageIO as oiio

from scenesplat_stereo import encode_pool
from scenesplat_stereo.protocol import JPEG_QUALITY

ENCODER_MODES = ("auto", "threads", "processes")
JPEG_ENCODERS = ("cpu", "nvjpeg")  # where JPEGs are encoded: encoder workers, or the GPU (``nvjpeg``)

# Fixed so that EXR files do not carry the wall-clock time (byte-identical rebuilds).
_EXR_DATETIME = "1970:01:01 00:00:00"
_PNG_COMPRESSION_LEVEL = 6  # contact sheets and other images
# Masks are written here with zlib, not through OpenImageIO, which exposes neither zlib's strategy nor a
# way to write to memory: rows unfiltered, deflated at level 1 with the run-length strategy (Z_RLE). A
# 0/255 mask is long runs of one value, which Z_RLE codes without hash searches. Measured at 1752x1168
# (docs/benchmarks.md, issue 12): 4.2 ms and 5 KB per mask on the 16-core GPU host against 9.0 ms and
# 17 KB through OpenImageIO (Sub filter, level 1); 2.6-2.9 ms against 4.4 ms on a 2-core CPU.
_MASK_ZLIB_LEVEL = 1
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"\0\0\0\0IEND\xaeB`\x82"  # the empty IEND chunk with its CRC
_JPEG_SUBSAMPLING = "4:2:0"

# /dev/shm is used for scratch files only with this much room (containers often give it 64 MB; a few
# 1752x1168 images per encoder thread must fit), else the system temp folder.
_SHM_MIN_FREE = 1 << 30
_scratch_lock = threading.Lock()
_scratch: dict[str, str] = {}  # {"pid": ..., "dir": ...} of this process
_local = threading.local()


def _scratch_dir() -> str:
    """This process's private scratch folder (created on first use, removed at exit)."""
    pid = str(os.getpid())
    with _scratch_lock:
        if _scratch.get("pid") != pid:
            base = "/dev/shm" if _free_bytes("/dev/shm") >= _SHM_MIN_FREE else None
            path = tempfile.mkdtemp(prefix="scenesplat-encode-", dir=base)
            _scratch.update(pid=pid, dir=path)
            atexit.register(shutil.rmtree, path, True)
        return _scratch["dir"]


def _free_bytes(path: str) -> int:
    """Bytes free to us in the file system of ``path`` (0 if it is missing or not writable)."""
    if not os.access(path, os.W_OK):
        return 0
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def _scratch_path(ext: str) -> str:
    """A scratch file name owned by the calling thread (one per extension)."""
    if getattr(_local, "pid", None) != os.getpid():
        _local.pid = os.getpid()
        _local.paths = {}
    if ext not in _local.paths:
        _local.paths[ext] = os.path.join(_scratch_dir(), f"t{threading.get_ident()}.{ext}")
    return _local.paths[ext]


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8 by round(clip(x, 0, 1) * 255); uint8 passes through unchanged."""
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        return rgb
    if not np.issubdtype(rgb.dtype, np.floating):
        raise TypeError(f"image: expected uint8 or float in [0, 1], got dtype {rgb.dtype}")
    if not np.isfinite(rgb).all():
        raise ValueError(f"image: {int((~np.isfinite(rgb)).sum())} values are NaN or infinite")
    return np.rint(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def _write(arr: np.ndarray, ext: str, fmt: str, attrs: dict[str, object]) -> bytes:
    """Write arr [H, W, C] (C-contiguous) with OpenImageIO to a scratch file and return its bytes."""
    if arr.ndim != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"image: expected a non-empty [H, W, C] array, got shape {arr.shape}")
    arr = np.ascontiguousarray(arr)
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    for name, value in attrs.items():
        spec.attribute(name, value)
    path = _scratch_path(ext)
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise RuntimeError(f"OpenImageIO has no writer for .{ext}: {oiio.geterror()}")
    try:
        if not out.open(path, spec):
            raise RuntimeError(f"OpenImageIO could not open {path}: {out.geterror()}")
        if not out.write_image(arr):
            raise RuntimeError(f"OpenImageIO could not write {path}: {out.geterror()}")
        out.close()
        with open(path, "rb") as f:
            return f.read()
    finally:
        out.close()
        _remove(path)


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def encode_jpeg(rgb: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """RGB image [H, W, 3] (uint8, or float in [0, 1] rounded to uint8) -> JPEG bytes at ``quality``."""
    rgb = to_uint8(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"encode_jpeg: expected an [H, W, 3] image, got shape {rgb.shape}")
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"encode_jpeg: quality must be in 1..100, got {quality}")
    attrs = {"Compression": f"jpeg:{int(quality)}", "jpeg:subsampling": _JPEG_SUBSAMPLING}
    return _write(rgb, "jpg", "uint8", attrs)


def encode_png(image: np.ndarray) -> bytes:
    """8-bit image [H, W, C] (uint8, or float in [0, 1] rounded to uint8) -> PNG bytes (e.g. contact sheets)."""
    image = to_uint8(image)
    if image.ndim != 3:
        raise ValueError(f"encode_png: expected an [H, W, C] image, got shape {image.shape}")
    return _write(image, "png", "uint8", {"png:compressionLevel": _PNG_COMPRESSION_LEVEL})


def encode_mask_png(mask: np.ndarray) -> bytes:
    """Boolean mask [H, W] -> 8-bit single-channel PNG bytes holding 0 (False) and 255 (True): one IHDR
    (8-bit greyscale, no interlace), one IDAT (unfiltered rows, zlib Z_RLE) and IEND."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"encode_mask_png: expected a bool [H, W] mask, got {mask.dtype} {mask.shape}")
    return encode_mask_pngs(mask[None])[0]  # which checks the dtype and the size


def encode_mask_pngs(masks: np.ndarray) -> list[bytes]:
    """Boolean masks [T, H, W] -> T PNGs as ``encode_mask_png`` writes them; the rows of all T are laid
    out in one array (two array operations per sample instead of two per mask)."""
    masks = np.asarray(masks)
    if masks.dtype != np.bool_ or masks.ndim != 3 or 0 in masks.shape[1:]:
        raise ValueError(f"encode_mask_pngs: expected non-empty bool [T, H, W] masks, got {masks.dtype} {masks.shape}")
    t, h, w = masks.shape
    rows = np.zeros((t, h, w + 1), np.uint8)  # each row: filter type 0 (none), then its pixels
    np.negative(masks.view(np.uint8), out=rows[:, :, 1:])  # 1 -> 255 (uint8 wraps), 0 -> 0
    head = _PNG_SIGNATURE + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
    out = []
    for r in rows:
        deflate = zlib.compressobj(_MASK_ZLIB_LEVEL, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
        out.append(head + _png_chunk(b"IDAT", deflate.compress(r) + deflate.flush()) + _PNG_END)
    return out


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    """One PNG chunk: length, type, data, CRC-32 of type + data (big-endian)."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_depth_exr(depth: np.ndarray) -> bytes:
    """Depth [H, W] (world units along the camera z axis) -> single-channel float16 EXR bytes (ZIP).

    Values above float16's range (65504) become +inf; NaN is refused."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"encode_depth_exr: expected an [H, W] depth map, got shape {depth.shape}")
    if np.isnan(depth).any():
        raise ValueError(f"encode_depth_exr: depth has {int(np.isnan(depth).sum())} NaN values")
    attrs = {"compression": "zip", "DateTime": _EXR_DATETIME}
    return _write(depth[:, :, None], "exr", "half", attrs)


def decode_image(data: bytes, ext: str) -> np.ndarray:
    """Decode image bytes of type ``ext`` ("jpg", "png", "exr", with or without a dot) with OpenImageIO.

    Returns [H, W, C] in the file's pixel type: uint8 for JPEG and PNG, float32 for (half) EXR.
    Raises ValueError when the bytes do not decode.
    """
    ext = ext.lower().lstrip(".")
    path = _scratch_path("in." + ext)
    with open(path, "wb") as f:
        f.write(data)
    try:
        inp = oiio.ImageInput.open(path)
        if inp is None:
            raise ValueError(f"decode_image: not a readable .{ext} image ({len(data)} bytes): {oiio.geterror()}")
        try:
            spec = inp.spec()
            fmt = "float" if spec.format.basetype in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE) else "uint8"
            arr = inp.read_image(fmt)
            if arr is None or inp.has_error:
                raise ValueError(f"decode_image: truncated or corrupt .{ext} image: {inp.geterror()}")
        finally:
            inp.close()
    finally:
        _remove(path)
    return np.asarray(arr).reshape(spec.height, spec.width, spec.nchannels)


@dataclass
class SampleImages:
    """The rendered images of one sample, ready to encode (already uint8 / bool on the CPU).

    ``left``/``right`` [H, W, 3] uint8; ``targets`` [T, H, W, 3] uint8 and ``masks`` [T, H, W] bool in
    the order of ``target_ids`` (the Fibonacci direction index j of each target); ``depth`` [H, W] float32
    (left camera, world units) or None; ``meta`` the sample's JSON bytes. ``jpegs``: the colour images
    already encoded (on the GPU, ``nvjpeg``), member name -> bytes for every name of ``jpeg_members``;
    ``left``, ``right`` and ``targets`` are then None.
    """

    key: str
    left: np.ndarray | None
    right: np.ndarray | None
    targets: np.ndarray | None
    masks: np.ndarray
    target_ids: tuple[int, ...]
    meta: bytes
    depth: np.ndarray | None = None
    jpegs: dict[str, bytes] | None = None


def jpeg_members(target_ids: tuple[int, ...]) -> list[str]:
    """The JPEG members of a sample (SPEC section 5), in the order left, right, targets."""
    return ["left.jpg", "right.jpg"] + [f"target_{j:02d}.jpg" for j in target_ids]


def encode_sample(sample: SampleImages, quality: int = JPEG_QUALITY) -> dict[str, bytes]:
    """Encode one sample into its shard members (SPEC section 5): ``left.jpg``, ``right.jpg`` and
    ``target_<jj>.jpg`` (taken as they are from ``sample.jpegs`` when given), then ``encode_other_members``."""
    if sample.jpegs is not None:
        jpegs = dict(sample.jpegs)
    else:
        images = [sample.left, sample.right, *sample.targets]
        jpegs = {name: encode_jpeg(image, quality) for name, image in zip(jpeg_members(sample.target_ids), images)}
    return jpegs | encode_other_members(sample)


def encode_other_members(sample: SampleImages) -> dict[str, bytes]:
    """The members of a sample other than its JPEGs: ``mask_<jj>.png`` for each target direction jj,
    ``left_depth.exr`` when depth is given, and ``json``."""
    names = [f"mask_{j:02d}.png" for j in sample.target_ids]
    members = dict(zip(names, encode_mask_pngs(sample.masks))) if names else {}
    if sample.depth is not None:
        members["left_depth.exr"] = encode_depth_exr(sample.depth)
    members["json"] = sample.meta
    return members


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
    into a shared slot and wait while one of ``workers`` encoder processes (``encode_pool``, started once
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
        self._procs = encode_pool.process_pool(workers) if workers and mode == "processes" else None
        # one slot per thread: a free slot is always there for a running thread
        self._all_slots = encode_pool.take_slots(workers, _scratch_dir()) if self._procs is not None else []
        self._slots: queue.SimpleQueue = queue.SimpleQueue()
        for slot in self._all_slots:
            self._slots.put(slot)
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="encode") if workers else None
        self._queue: queue.Queue = queue.Queue(maxsize=self.max_pending)
        self._writer = None
        if self._pool is not None:
            self._writer = threading.Thread(target=self._write_loop, name="shard-writer", daemon=True)
            self._writer.start()

    def _encode(self, sample: SampleImages) -> dict[str, bytes]:
        t0 = time.perf_counter()
        members = encode_sample(sample, self.quality) if self._procs is None else self._encode_in_process(sample)
        with self._time_lock:
            self.encode_s += time.perf_counter() - t0
        return members

    def _encode_in_process(self, sample: SampleImages) -> dict[str, bytes]:
        slot = self._slots.get()
        try:
            names = ("masks", "depth") + (() if sample.jpegs is not None else ("left", "right", "targets"))
            arrays = {n: getattr(sample, n) for n in names if getattr(sample, n) is not None}
            path, layout = slot.put(arrays)
            future = self._procs.submit(encode_pool.encode_in_worker, path, layout, sample.key,
                                        tuple(sample.target_ids), sample.meta, self.quality)
            try:
                return (sample.jpegs or {}) | future.result()
            except BrokenProcessPool:
                encode_pool.discard_pool(self.workers, self._procs)
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

    def submit(self, sample: SampleImages) -> None:
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
        encode_pool.give_back_slots(self._all_slots)
        self._all_slots = []

    def __enter__(self) -> SampleEncoder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
