"""JPEG encoding on the GPU through NVIDIA's nvJPEG library (``build --jpeg-encoder nvjpeg``), optional.

The build's host encoder (OpenImageIO/libjpeg-turbo, ``encode.py``) is the default and the reference. On a
CUDA machine with nvJPEG, the colour images of a rendered batch can be encoded where they were rendered:
only the JPEG bytes (and the masks) travel to the host, and the host's encoder workers write the mask PNGs
alone. Measured in ``docs/benchmarks.md`` (issue 12): the JPEGs were 12 of the 22 files and about two
thirds of the host's encode time per pair at 1752x1168.

Settings as SPEC section 4 and ``encode.encode_jpeg``: quality 92 (``nvjpegEncoderParamsSetQuality``,
the IJG scaling of the standard tables), 4:2:0 chroma subsampling (``NVJPEG_CSS_420``), baseline
sequential DCT with the standard Huffman tables. The pixels are the same uint8 RGB as the host path's;
the bytes are not (nvJPEG's colour conversion, downsampling and DCT round differently from
libjpeg-turbo's): docs/benchmarks.md gives the size and PSNR of both on the same images. The same input
on the same GPU model and nvJPEG version gives the same bytes (tested), which is what a resumed or
repeated build needs.

The library is found, in order, at ``$SCENESPLAT_NVJPEG`` (a path), in the ``nvidia-nvjpeg`` pip
packages (``nvidia/nvjpeg/lib`` or ``nvidia/cu*/lib`` on ``sys.path``), then by the system loader
(``libnvjpeg.so.13``, ``.12``, ``.11``, ``libnvjpeg.so``: the CUDA toolkit). It is called through
``ctypes``: no compiled extension, and nothing is loaded unless the option is used. torchvision's
``encode_jpeg`` also calls nvJPEG but cannot subsample chroma (its files are 1.76x larger) and is not
installable beside our CPU torch wheel, hence our own binding of the dozen calls we need.

Usage: ``enc = NvJpegEncoder(device)``; ``future = enc.encode(images)`` queues the encoding of ``images``
[N, H, W, 3] uint8 (CUDA) after the work already queued on the current stream, and returns at once;
``future.result()`` gives the N files' bytes, in order.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor

import torch

from scenesplat_stereo.common.commandline import NotAvailable
from scenesplat_stereo.shards.sample import JPEG_QUALITY

# nvjpeg.h constants
_CSS = {"4:4:4": 0, "4:2:2": 1, "4:2:0": 2}  # nvjpegChromaSubsampling_t
_INPUT_RGBI = 5  # nvjpegInputFormat_t: interleaved RGB
_ENCODING_BASELINE_DCT = 0xC0  # nvjpegJpegEncoding_t
_STATUS = {1: "not initialized", 2: "invalid parameter", 3: "bad JPEG", 4: "JPEG not supported",
           5: "allocator failure", 6: "execution failed", 7: "architecture mismatch", 8: "internal error",
           9: "implementation not supported", 10: "incomplete bitstream"}
_SONAMES = ("libnvjpeg.so.13", "libnvjpeg.so.12", "libnvjpeg.so.11", "libnvjpeg.so")
INSTALL_HINT = ("nvJPEG ships with the CUDA toolkit; or `pip install nvidia-nvjpeg` (CUDA 13) / "
                "`pip install nvidia-nvjpeg-cu12` (CUDA 12); or set SCENESPLAT_NVJPEG=/path/to/libnvjpeg.so")


class _Image(ctypes.Structure):
    """nvjpegImage_t: up to 4 channel pointers and their pitches (bytes)."""

    _fields_ = [("channel", ctypes.c_void_p * 4), ("pitch", ctypes.c_size_t * 4)]


_lib_lock = threading.Lock()
_lib: list[ctypes.CDLL] = []


def _candidates() -> list[str]:
    paths = [os.environ["SCENESPLAT_NVJPEG"]] if os.environ.get("SCENESPLAT_NVJPEG") else []
    for base in sys.path:
        for sub in ("nvidia/nvjpeg/lib", "nvidia/cu13/lib", "nvidia/cu12/lib"):
            paths += sorted(glob.glob(os.path.join(base, sub, "libnvjpeg.so*")), reverse=True)
    found = ctypes.util.find_library("nvjpeg")
    return paths + list(_SONAMES) + ([found] if found else [])


def load_library() -> ctypes.CDLL:
    """The nvJPEG library (loaded once); ``NotAvailable`` naming where it was looked for when it is missing."""
    with _lib_lock:
        if not _lib:
            tried = []
            for path in _candidates():
                try:
                    lib = ctypes.CDLL(path)
                except OSError as e:
                    tried.append(f"{path} ({e})" if os.sep in path else path)
                    continue
                _declare(lib)
                _lib.append(lib)
                break
            else:
                raise NotAvailable(f"--jpeg-encoder nvjpeg: nvJPEG not found (tried {', '.join(tried)}). "
                                   + INSTALL_HINT)
        return _lib[0]


def _declare(lib: ctypes.CDLL) -> None:
    vp, st, i = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int
    signatures = {
        "nvjpegCreateSimple": [ctypes.POINTER(vp)],
        "nvjpegDestroy": [vp],
        "nvjpegEncoderStateCreate": [vp, ctypes.POINTER(vp), vp],
        "nvjpegEncoderStateDestroy": [vp],
        "nvjpegEncoderParamsCreate": [vp, ctypes.POINTER(vp), vp],
        "nvjpegEncoderParamsDestroy": [vp],
        "nvjpegEncoderParamsSetQuality": [vp, i, vp],
        "nvjpegEncoderParamsSetSamplingFactors": [vp, i, vp],
        "nvjpegEncoderParamsSetEncoding": [vp, i, vp],
        "nvjpegEncoderParamsSetOptimizedHuffman": [vp, i, vp],
        "nvjpegEncodeImage": [vp, vp, vp, ctypes.POINTER(_Image), i, i, i, vp],
        "nvjpegEncodeRetrieveBitstream": [vp, vp, vp, ctypes.POINTER(st), vp],
    }
    for name, args in signatures.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, ctypes.c_int


def _check(status: int, call: str) -> None:
    if status != 0:
        raise RuntimeError(f"nvJPEG {call} failed: status {status} ({_STATUS.get(status, 'unknown')})")


class NvJpegEncoder:
    """nvJPEG encoder for one CUDA device: quality ``quality`` (1..100), ``subsampling`` "4:2:0" (SPEC),
    "4:2:2" or "4:4:4", baseline coding, standard Huffman tables.

    ``encode`` hands the work to the encoder's own thread and stream, and returns at once: the caller (the
    build's render loop) goes on rendering while the JPEGs are encoded and read back. That matters
    because ``nvjpegEncodeImage`` blocks its host thread for about 0.17 ms per image whatever the image
    size (H100, docs/benchmarks.md). The thread waits on the GPU for the caller's stream (an event), runs
    every nvJPEG call (an nvJPEG state is not thread-safe; ctypes releases the GIL during each call),
    queries the bitstream lengths, and reads all the bitstreams into one pinned host buffer. Each image in
    flight needs its own nvJPEG encoder state (its device buffers hold the bitstream until it is read);
    states are pooled and reused, so a steady build allocates nothing."""

    def __init__(self, device: torch.device | str, quality: int = JPEG_QUALITY, subsampling: str = "4:2:0") -> None:
        if not 1 <= int(quality) <= 100:
            raise ValueError(f"nvJPEG: quality must be in 1..100, got {quality}")
        if subsampling not in _CSS:
            raise ValueError(f"nvJPEG: subsampling must be one of {list(_CSS)}, got {subsampling!r}")
        device = torch.device(device)
        if device.type != "cuda":
            raise ValueError(f"--jpeg-encoder nvjpeg needs a CUDA device, got {device}")
        self.device = torch.device("cuda", torch.cuda.current_device() if device.index is None else device.index)
        self.lib = load_library()
        self.quality, self.subsampling = int(quality), subsampling
        self._handle, self._params = ctypes.c_void_p(), ctypes.c_void_p()
        self._free: list[ctypes.c_void_p] = []
        with torch.cuda.device(self.device):
            self._stream = torch.cuda.Stream(self.device)
            _check(self.lib.nvjpegCreateSimple(ctypes.byref(self._handle)), "nvjpegCreateSimple")
            _check(self.lib.nvjpegEncoderParamsCreate(self._handle, ctypes.byref(self._params), None),
                   "nvjpegEncoderParamsCreate")
            for call, value in (("SetQuality", self.quality), ("SetSamplingFactors", _CSS[subsampling]),
                                ("SetEncoding", _ENCODING_BASELINE_DCT), ("SetOptimizedHuffman", 0)):
                _check(getattr(self.lib, "nvjpegEncoderParams" + call)(self._params, value, None),
                       "nvjpegEncoderParams" + call)
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="nvjpeg", initializer=torch.cuda.set_device,
                                          initargs=(self.device,))

    def encode(self, images: torch.Tensor, stream: torch.cuda.Stream | None = None) -> Future:
        """Encode ``images`` [N, H, W, 3] (uint8, on this device) once the work queued so far on ``stream``
        (default: the current stream) is done; returns at once. ``result()`` of the returned future gives
        the N files' bytes in order (or raises what nvJPEG raised)."""
        if images.dtype != torch.uint8 or images.dim() != 4 or images.shape[-1] != 3:
            raise ValueError(f"nvJPEG: expected [N, H, W, 3] uint8 images, got {images.dtype} {list(images.shape)}")
        if images.device != self.device:
            raise ValueError(f"nvJPEG: images are on {images.device}, the encoder on {self.device}")
        stream = stream if stream is not None else torch.cuda.current_stream(self.device)
        with torch.cuda.stream(stream):
            images = images.contiguous()
        ready = torch.cuda.Event()
        ready.record(stream)
        return self._thread.submit(self._encode_now, images, ready)

    def _state(self) -> ctypes.c_void_p:
        if self._free:
            return self._free.pop()
        state = ctypes.c_void_p()
        _check(self.lib.nvjpegEncoderStateCreate(self._handle, ctypes.byref(state), None), "nvjpegEncoderStateCreate")
        return state

    def _encode_now(self, images: torch.Tensor, ready: torch.cuda.Event) -> list[bytes]:
        """On the encoder thread: encode, wait, read the bitstreams back (``images`` stays referenced until
        the GPU is done with it)."""
        n, h, w, _ = images.shape
        stream = self._stream.cuda_stream
        self._stream.wait_event(ready)
        states = [self._state() for _ in range(n)]
        try:
            for k, state in enumerate(states):
                image = _Image()
                image.channel[0] = images[k].data_ptr()
                image.pitch[0] = 3 * w
                _check(self.lib.nvjpegEncodeImage(self._handle, state, self._params, ctypes.byref(image),
                                                  _INPUT_RGBI, w, h, stream), "nvjpegEncodeImage")
            lengths = []
            for state in states:
                length = ctypes.c_size_t(0)
                _check(self.lib.nvjpegEncodeRetrieveBitstream(self._handle, state, None, ctypes.byref(length), stream),
                       "nvjpegEncodeRetrieveBitstream")
                lengths.append(length.value)
            host = torch.empty(sum(lengths), dtype=torch.uint8, pin_memory=True)
            offsets = [0]
            for state, size in zip(states, lengths):
                length = ctypes.c_size_t(size)
                _check(self.lib.nvjpegEncodeRetrieveBitstream(self._handle, state, host.data_ptr() + offsets[-1],
                                                              ctypes.byref(length), stream),
                       "nvjpegEncodeRetrieveBitstream")
                offsets.append(offsets[-1] + size)
        finally:
            self._stream.synchronize()
            self._free.extend(states)
        data = host.numpy()
        return [data[a:b].tobytes() for a, b in zip(offsets[:-1], offsets[1:])]  # one copy per file

    def close(self) -> None:
        """Stop the encoder thread; free the nvJPEG states, parameters and handle (also at garbage collection)."""
        if getattr(self, "_handle", None) is None or not self._handle:
            return
        self._thread.shutdown(wait=True)
        for state in self._free:
            self.lib.nvjpegEncoderStateDestroy(state)
        self._free = []
        self.lib.nvjpegEncoderParamsDestroy(self._params)
        self.lib.nvjpegDestroy(self._handle)
        self._handle = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001  (interpreter shutdown: the library may be gone)
            pass
