"""Warp runtime glue for the rasteriser: the one place that initialises Warp, turns torch tensors into
kernel arguments and launches kernels.

Kernels run on the device of the torch inputs ("cpu" or "cuda:i"), on torch's current CUDA stream, so
torch and Warp work is ordered without explicit synchronisation. Arguments are zero-copy array
descriptors of torch tensors (``to_wp``). ``launch`` replays a launch command recorded once per kernel,
device and thread (Warp's ``record_cmd``), setting only the arguments and, when it changed, the grid: a
full ``wp.launch`` re-validates and re-packs every argument, and at rendering sizes the host time of the
launches, not the GPU, set the pace of a single-scene render (docs/benchmarks.md, "Host time").
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import tempfile
import threading
from dataclasses import dataclass

import torch
import warp as wp

#: What Warp's native library prints (C stdio, past Python's sys.stderr) on a machine without the CUDA driver: every
#: command would start with it; our own device checks say "no CUDA device" where a command asked for one.
NO_DRIVER_NOTICE = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def _init_quietly() -> None:
    """``wp.init()``; without a CUDA driver (torch sees no GPU), the native stderr (file descriptor 2) goes to a
    temp file meanwhile and all of it but ``NO_DRIVER_NOTICE`` is printed back."""
    if torch.cuda.is_available():
        wp.init()
        return
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            rest = [line for line in caught.read().decode(errors="replace").splitlines(keepends=True)
                    if not line.startswith(NO_DRIVER_NOTICE)]
    sys.stderr.write("".join(rest))


wp.config.log_level = wp.LOG_WARNING  # no banner or per-module compile lines
_init_quietly()

# SPEC section 2, step 6: a Gaussian touches a pixel when o * exp(-sigma) >= 1/255.
ALPHA_MIN = 1.0 / 255.0
# SPEC section 2, step 7: compositing stops before T would drop to or below this.
T_MIN = 1e-4

# Warp's low-level array descriptor (what ``wp.from_torch(..., return_ctype=True)`` returns), built
# directly in ``to_wp``; ``_NULL`` replaces a recorded launch's arrays once it is queued.
_DESCRIPTOR = type(wp.from_torch(torch.zeros(1), requires_grad=False, return_ctype=True))
_NULL = _DESCRIPTOR()
_SCALARS = {torch.float32: wp.float32, torch.float64: wp.float64, torch.int32: wp.int32, torch.int64: wp.int64,
            torch.uint8: wp.uint8, torch.int16: wp.int16}


def warp_device(t: torch.Tensor) -> str:
    """The Warp device string for a torch tensor's device."""
    if t.device.type == "cuda":
        return f"cuda:{t.device.index if t.device.index is not None else torch.cuda.current_device()}"
    if t.device.type != "cpu":
        raise ValueError(f"rasterization runs on CPU or CUDA tensors, got device {t.device}")
    return "cpu"


_ELEMENTS: dict = {}  # (torch dtype, Warp dtype or None) -> (component shape, element bytes), see _element


def _element(tensor_dtype: torch.dtype, dtype) -> tuple[tuple[int, ...], int]:
    """(component shape, bytes) of Warp elements of ``dtype`` (scalar, vector or matrix; None: the tensor's
    own scalar type) read from a tensor of ``tensor_dtype``; checked once per pair, then looked up."""
    key = (tensor_dtype, dtype)
    if key not in _ELEMENTS:
        scalar = _SCALARS.get(tensor_dtype)
        dtype = scalar if dtype is None else dtype
        composite = wp.types.type_is_vector(dtype) or wp.types.type_is_matrix(dtype)
        if scalar is None or (dtype._wp_scalar_type_ if composite else dtype) is not scalar:
            raise TypeError(f"to_wp: a {tensor_dtype} tensor cannot hold {dtype} elements")
        _ELEMENTS[key] = (tuple(dtype._shape_) if composite else (), wp.types.type_size_in_bytes(dtype))
    return _ELEMENTS[key]


def to_wp(t: torch.Tensor, dtype=None, shape=None):
    """Zero-copy kernel argument for a torch tensor: ``dtype`` may group the trailing axis (vectors) or two
    axes (matrices) into elements; ``shape`` is the array shape in elements (default: the tensor's leading
    axes, with their strides, so a strided view such as one field of a packed gradient is read in place;
    a given ``shape`` needs a contiguous tensor and copies any other). Returns Warp's low-level array
    descriptor, which keeps the tensor alive. Outputs must be contiguous tensors (a copy would be written)."""
    components, nbytes = _ELEMENTS.get((t.dtype, dtype)) or _element(t.dtype, dtype)
    k = len(components)
    strides = None
    if shape is None:
        lead = t.dim() - k
        if t.shape[lead:] != components:
            raise ValueError(f"to_wp: a {tuple(t.shape)} tensor does not end in {dtype} components {components}")
        dense = ((components[-1], 1) if k == 2 else (1,) if k == 1 else ())
        if lead and not t.is_contiguous() and t.stride()[lead:] == dense:  # a strided view, read in place
            strides = [s * t.element_size() for s in t.stride()[:lead]]
        else:
            t = t.contiguous()
        shape = t.shape[:lead] or (1,)
    else:
        t = t.contiguous()
        if math.prod(shape) * math.prod(components) != t.numel():
            raise ValueError(f"to_wp: {tuple(t.shape)} is not {tuple(shape)} elements of {components}")
    if strides is None:  # contiguous elements (one and two axes spelled out: this runs ~35 times a frame)
        if len(shape) == 1:
            strides = (nbytes,)
        elif len(shape) == 2:
            strides = (shape[1] * nbytes, nbytes)
        else:
            strides = [nbytes] * len(shape)
            for i in range(len(shape) - 2, -1, -1):
                strides[i] = strides[i + 1] * shape[i + 1]
    desc = _DESCRIPTOR(t.data_ptr(), 0, len(shape), shape, strides)
    desc._ref = t  # as wp.from_torch: the tensor lives as long as the descriptor
    return desc


@dataclass
class _Command:
    """A recorded launch: the Warp command, its current grid and the parameter slots holding arrays."""

    launch: object  # wp.Launch
    dim: tuple[int, ...]
    array_slots: tuple[int, ...]


class _Commands(threading.local):
    """Recorded launches of the calling thread, by (kernel, device, block_dim)."""

    def __init__(self):
        self.by_key: dict[tuple, _Command] = {}


_COMMANDS = _Commands()
_STREAMS: dict[tuple[int, int], wp.Stream] = {}  # Warp wrappers of torch CUDA streams, by (device, handle)


def _stream(t: torch.Tensor) -> wp.Stream:
    """Warp's view of torch's current stream on the tensor's CUDA device (a wrapper made once per stream;
    the handle is read with the call torch's own compiler uses, a tenth of ``torch.cuda.current_stream``'s
    host time)."""
    key = (t.device.index, torch._C._cuda_getCurrentRawStream(t.device.index))
    stream = _STREAMS.get(key)
    if stream is None:
        stream = _STREAMS[key] = wp.stream_from_torch(torch.cuda.current_stream(t.device))
    return stream


def launch(kernel, dim: int | tuple[int, ...], args: list, like: torch.Tensor, block_dim: int = 0) -> None:
    """Run ``kernel`` over the grid ``dim`` with its arguments in order (``to_wp`` descriptors, ints,
    floats) on the device of ``like`` and, on CUDA, on torch's current stream there. ``block_dim`` > 0
    launches a cooperative kernel as ``wp.launch_tiled`` does: ``dim`` blocks of ``block_dim`` threads
    (on the CPU, Warp's fibers)."""
    device = warp_device(like)
    dim = (*(dim if isinstance(dim, tuple) else (dim,)), *((block_dim,) if block_dim else ()))
    if math.prod(dim) == 0:
        return
    key = (kernel, device, block_dim)
    cmd = _COMMANDS.by_key.get(key)
    with _cpu_blocks(device) if block_dim else contextlib.nullcontext():
        if cmd is None:
            recorded = wp.launch(kernel, dim=dim, inputs=args, device=device, block_dim=block_dim or None,
                                 record_cmd=True)
            recorded.fwd_args = None  # kept by Warp only for its own graph capture; would keep our tensors alive
            slots = tuple(i + 1 for i, a in enumerate(kernel.adj.args) if wp.types.is_array(a.type))
            cmd = _COMMANDS.by_key[key] = _Command(recorded, dim, slots)
        else:
            if cmd.dim != dim:
                cmd.launch.set_dim(dim)
                cmd.dim = dim
            for i, a in enumerate(args):
                cmd.launch.set_param_at_index_from_ctype(i, a)
        cmd.launch.launch(None if device == "cpu" else _stream(like))
    for slot in cmd.array_slots:  # queued: let the tensors go (the next launch sets every argument again)
        cmd.launch.params[slot] = _NULL


def radix_sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int) -> None:
    """Stable in-place sort of the first ``count`` (key, value) pairs by key bits [0, end_bit) (Warp's
    radix sort; ``keys`` int64 and ``values`` 4-byte, each with room for 2 ``count`` entries)."""
    wk, wv = wp.from_torch(keys), wp.from_torch(values)
    scope = contextlib.nullcontext() if keys.device.type == "cpu" else wp.ScopedStream(_stream(keys), sync_enter=False)
    with scope:
        wp.utils.radix_sort_pairs(wk, wv, count, begin_bit=0, end_bit=end_bit)


def vector_type(length: int):
    """The Warp float32 vector type of a given length (the channel count D of a compositing variant)."""
    return wp.types.vector(length=length, dtype=wp.float32)


@contextlib.contextmanager
def _cpu_blocks(device: str):
    """Cooperative (tiled) kernels need real thread blocks; on the CPU Warp runs them as fibers only when
    ``enable_cpu_blocks`` is set, so set it around such launches."""
    if device != "cpu":
        yield
        return
    previous = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        yield
    finally:
        wp.config.enable_cpu_blocks = previous
