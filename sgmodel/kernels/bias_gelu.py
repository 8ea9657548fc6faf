"""Triton kernels of GELU(x + bias) on channels-last tensors (``sgmodel.model.layers.bias_gelu``: a convolution's
bias and the GELU after it, in the decoder).

Imported only on CUDA with Triton present; ``layers.bias_gelu`` runs ``F.gelu(x + bias)`` everywhere else,
and that path in float64 is the reference the kernels are tested against (tests/sgmodel/model/test_layers.py).

A channels-last tensor [B, C, H, W] is the row-major array [M, C] (M = B H W pixels); a program reads a
tile of pixels x all channels. Forward: y = GELU(x + b) with a = x + b in float32 (PyTorch's separate bias
addition rounds a to x's dtype first), the exact (erf) GELU of ``group_norm_kernels``, written in x's dtype.
Backward: dx = dy GELU'(x + b), written in x's dtype, and the bias gradient in the same pass: each program
sums its float32 dx over its pixels into one row of partial sums, which are added up here (no atomics:
the same sum every run). Without these kernels the bias is a broadcast addition over the whole output
(slow in channels-last), the GELU another pass, and the bias gradient a reduction of its own.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from sgmodel.kernels.group_norm import _gelu_and_slope

_BLOCK_M = 32  # pixels of one tile
_TILES = 16  # tiles one backward program walks (its partial bias-gradient row covers them all)


@triton.jit
def _bias_gelu_forward_kernel(x_ptr, b_ptr, y_ptr, M, C, BLOCK_M: tl.constexpr, BLOCK_C: tl.constexpr):
    m = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    c = tl.arange(0, BLOCK_C)
    mask = (m < M)[:, None] & (c < C)[None, :]
    offs = m.to(tl.int64)[:, None] * C + c[None, :]
    a = tl.load(x_ptr + offs, mask=mask, other=0.0).to(tl.float32) + \
        tl.load(b_ptr + c, mask=c < C, other=0.0).to(tl.float32)[None, :]
    y, _ = _gelu_and_slope(a)
    tl.store(y_ptr + offs, y.to(y_ptr.dtype.element_ty), mask=mask)


@triton.jit
def _bias_gelu_backward_kernel(g_ptr, x_ptr, b_ptr, dx_ptr, partial_ptr, M, C, BLOCK_M: tl.constexpr,
                               BLOCK_C: tl.constexpr, TILES: tl.constexpr):
    pid = tl.program_id(0)
    c = tl.arange(0, BLOCK_C)
    bias = tl.load(b_ptr + c, mask=c < C, other=0.0).to(tl.float32)[None, :]
    db = tl.zeros((BLOCK_C,), dtype=tl.float32)
    for t in range(TILES):
        m = (pid * TILES + t) * BLOCK_M + tl.arange(0, BLOCK_M)
        mask = (m < M)[:, None] & (c < C)[None, :]
        offs = m.to(tl.int64)[:, None] * C + c[None, :]
        _, slope = _gelu_and_slope(tl.load(x_ptr + offs, mask=mask, other=0.0).to(tl.float32) + bias)
        dx = tl.load(g_ptr + offs, mask=mask, other=0.0).to(tl.float32) * slope
        tl.store(dx_ptr + offs, dx.to(dx_ptr.dtype.element_ty), mask=mask)
        db += tl.sum(tl.where(mask, dx, 0.0), axis=0)
    tl.store(partial_ptr + pid * C + c, db, mask=c < C)


def forward(x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """GELU(x + bias) of a channels-last CUDA tensor x [B, C, H, W], channels-last in x's dtype."""
    C = x.shape[1]
    M = x.numel() // C
    y = torch.empty_like(x, memory_format=torch.channels_last)
    _bias_gelu_forward_kernel[(triton.cdiv(M, _BLOCK_M),)](x, bias, y, M, C, BLOCK_M=_BLOCK_M,
                                                           BLOCK_C=triton.next_power_of_2(C))
    return y


def backward(grad: torch.Tensor, x: torch.Tensor, bias: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(dx in x's dtype, channels-last; dbias float32 [C]) from dL/dy ``grad`` (one pass writes both)."""
    C = x.shape[1]
    M = x.numel() // C
    grad = grad.contiguous(memory_format=torch.channels_last)
    dx = torch.empty_like(x, memory_format=torch.channels_last)
    programs = triton.cdiv(M, _BLOCK_M * _TILES)
    partial = torch.empty(programs, C, device=x.device, dtype=torch.float32)
    _bias_gelu_backward_kernel[(programs,)](grad, x, bias, dx, partial, M, C, BLOCK_M=_BLOCK_M,
                                            BLOCK_C=triton.next_power_of_2(C), TILES=_TILES)
    return dx, partial.sum(0)
