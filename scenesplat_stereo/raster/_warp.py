"""Warp runtime glue for the rasteriser: one place that initialises Warp and moves torch tensors in.

Kernels run on the device of the torch inputs ("cpu" or "cuda:i"), on torch's current CUDA stream, so
torch and Warp work is ordered without explicit synchronisation. Arrays are zero-copy views of torch
tensors (``wp.from_torch``); every kernel module is compiled once per variant and cached by Warp.
"""

from __future__ import annotations

import contextlib

import torch
import warp as wp

wp.config.log_level = wp.LOG_WARNING  # no banner or per-module compile lines
wp.init()

# SPEC section 2, step 6: a Gaussian touches a pixel when o * exp(-sigma) >= 1/255.
ALPHA_MIN = 1.0 / 255.0
# SPEC section 2, step 7: compositing stops before T would drop to or below this.
T_MIN = 1e-4


def warp_device(t: torch.Tensor) -> str:
    """The Warp device string for a torch tensor's device."""
    if t.device.type == "cuda":
        return f"cuda:{t.device.index if t.device.index is not None else torch.cuda.current_device()}"
    if t.device.type != "cpu":
        raise ValueError(f"rasterization runs on CPU or CUDA tensors, got device {t.device}")
    return "cpu"


def to_wp(t: torch.Tensor, dtype=None, shape=None):
    """Zero-copy kernel argument for a torch tensor: ``dtype`` may group the trailing axis (vectors) or two
    axes (matrices) into elements; ``shape`` is the array shape in elements. Returns Warp's low-level array
    descriptor, which launches take directly at a fraction of the cost of a ``wp.array``. Outputs must be
    contiguous tensors (a non-contiguous one would be copied, and the kernel would write to the copy)."""
    t = t.contiguous()
    if shape is not None:
        components = 2 if wp.types.type_is_matrix(dtype) else 1 if wp.types.type_is_vector(dtype) else 0
        t = t.reshape(*shape, *t.shape[t.dim() - components:])
    return wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)


@contextlib.contextmanager
def on_device_of(t: torch.Tensor):
    """Run Warp launches on the tensor's device and, on CUDA, on torch's current stream."""
    device = warp_device(t)
    if device == "cpu":
        with wp.ScopedDevice("cpu"):
            yield device
    else:
        with wp.ScopedDevice(device), wp.ScopedStream(wp.stream_from_torch(t.device)):
            yield device


def vector_type(length: int):
    """The Warp float32 vector type of a given length (the channel count D of a compositing variant)."""
    return wp.types.vector(length=length, dtype=wp.float32)


@contextlib.contextmanager
def cpu_blocks(device: str):
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
