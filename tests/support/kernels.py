"""Where the tests of our Triton kernels run them: on CUDA where there is a GPU, else on the CPU under Triton's
interpreter in a process started with ``TRITON_INTERPRET=1`` (``sgmodel.kernels``' docstring), else nowhere (the
tests skip, saying how to run them). Marked ``kernels``: ``TRITON_INTERPRET=1 python -m pytest -m kernels`` runs
them on a machine without a GPU (the concatenation's and SSIM's kernel tests are not marked: CUDA only)."""

from __future__ import annotations

import math

import pytest
import torch

from sgmodel.kernels import triton_installed, triton_interpreted

#: the device the kernel tests put their tensors on
KERNEL_DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
#: the most elements a tested tensor has under the interpreter (larger cases run on CUDA only, which keeps the
#: interpreter's run near a minute on 2 cores)
INTERPRETED_ELEMENTS = 1 << 20


def _where() -> str | None:
    if not triton_installed():
        return "Triton is not installed"
    if not torch.cuda.is_available() and not triton_interpreted():
        return "needs CUDA, or Triton's interpreter on the CPU: TRITON_INTERPRET=1 python -m pytest -m kernels"
    return None


def kernel_test(fn):
    """Marks a test of the Triton kernels (``kernels``) and skips it where they cannot run."""
    reason = _where()
    return pytest.mark.kernels(pytest.mark.skipif(reason is not None, reason=reason or "")(fn))


def interpret_only_if(keep: bool, why: str) -> None:
    """Under the interpreter, skips the calling test case unless ``keep``: there a few cases stand for the rest,
    which run on CUDA (``why``: what the interpreter cannot do fast or the same)."""
    if KERNEL_DEVICE == "cpu" and not keep:
        pytest.skip(f"on CUDA only: {why}")


def skip_if_too_large_to_interpret(*shapes: tuple[int, ...]) -> None:
    """Skips the calling test under the interpreter when a tensor of ``shapes`` has more than
    ``INTERPRETED_ELEMENTS`` elements (it runs on CUDA)."""
    interpret_only_if(max(math.prod(s) for s in shapes) <= INTERPRETED_ELEMENTS,
                      f"{max(shapes, key=math.prod)} is too large for Triton's interpreter")
