"""Every GPU kernel of the model, and the one place that says whether they run.

The Triton kernels (``bias_gelu``, ``composer``, ``concat``, ``group_norm``, ``lpips_tap``, ``ssim``,
``upsample``) and the Warp soft-argmin of PSMNet's disparity regression (``soft_argmin``): each module holds a
forward and, where training needs one, a backward; the operation that dispatches to it (``sgmodel.model.layers``,
``sgmodel.model.composer``, ``sgmodel.metrics``) keeps its PyTorch path as the reference it is tested against
(in float64, or against that path tested in float64). Public names here: ``triton_installed``,
``triton_runs_on``, ``triton_kernels_run``, ``channels_last_kernels_run``, ``CAT_KERNEL_SOURCES``. This package
and ``scenesplat_stereo.raster`` are the only ones that import Warp or Triton (tests/test_import_cycles.py);
importing this package itself imports neither.

The Triton kernels run on CUDA tensors, and (but for ``concat``'s and ``ssim``'s, which Triton's interpreter cannot
run as written) on CPU tensors in a process started with ``TRITON_INTERPRET=1``: the interpreter then runs each
kernel program in numpy (some thousand times slower than a GPU; float32 arithmetic as IEEE operations, half
precision rounded its own way). That is how the kernels are tested on a machine without a GPU
(``TRITON_INTERPRET=1 python -m pytest -m kernels``); the variable must be set before Triton is imported, since
Triton decides at import which of its own functions are interpreted.
"""

from __future__ import annotations

import functools
import importlib.util
import os

import torch

#: the most tensors ``layers.cat_channels`` concatenates in one launch of ``concat``'s kernel (its source slots)
CAT_KERNEL_SOURCES = 3


def triton_runs_on(x: torch.Tensor) -> bool:
    """Whether our Triton kernels can run on ``x``'s device: CUDA with Triton installed, or the CPU under Triton's
    interpreter (module docstring)."""
    return triton_installed() and (x.is_cuda or (x.device.type == "cpu" and triton_interpreted()))


def triton_kernels_run(x: torch.Tensor) -> bool:
    """Whether our Triton kernels of 4D activations take ``x``: a 4D tensor in float32, float16 or bfloat16 on a
    device they run on (``triton_runs_on``; ``channels_last_kernels_run``; LPIPS's tap distance in any strides)."""
    return x.dim() == 4 and x.dtype in (torch.float32, torch.float16, torch.bfloat16) and triton_runs_on(x)


def channels_last_kernels_run(x: torch.Tensor) -> bool:
    """Whether the Triton kernels for channels-last activations (``group_norm_gelu``, ``bias_gelu``,
    ``upsample_bilinear``'s 2x) run for ``x``: ``triton_kernels_run`` and channels-last."""
    return triton_kernels_run(x) and x.is_contiguous(memory_format=torch.channels_last)


@functools.cache
def triton_interpreted() -> bool:
    """Whether this process runs Triton's kernels in its interpreter (``TRITON_INTERPRET=1``)."""
    return os.environ.get("TRITON_INTERPRET") == "1"


@functools.cache
def triton_installed() -> bool:
    """Whether Triton can be imported (the fused GroupNorm kernels; torch.compile's GPU code)."""
    return importlib.util.find_spec("triton") is not None
