"""Triton kernels of the 2x bilinear upsampling of channels-last tensors (``sgmodel.model.layers.upsample_bilinear``).

Imported only on CUDA with Triton present; elsewhere ``layers.upsample_bilinear`` runs ``F.interpolate``,
which is also the reference the kernels are tested against (tests/sgmodel/model/test_layers.py).

PyTorch's bilinear resize (``align_corners=False``) from n to 2n along an axis reads, for output o, the
source position s = max(0.5 (o + 0.5) - 0.5, 0), its pixels i0 = floor(s) and i1 = i0 + (i0 < n - 1), with
weights 1 - l and l (l = s - i0); in 2D, out = (1 - ly)((1 - lx) x00 + lx x01) + ly((1 - lx) x10 + lx x11),
in float32. The forward kernel computes exactly that for a tile of output pixels x channels and writes it
in the consumer's dtype (the decoder's last upsampling feeds a bf16 convolution: one bf16 write instead of a
float32 one and a cast). The backward gathers instead of scattering: input pixel i receives from the
outputs 2i - 1 .. 2i + 2 of each axis the weight with which each read it (PyTorch's backward adds with
atomics, in a run-dependent order), so every input gradient is one float32 sum, written once.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

_BLOCK_P = 64  # pixels of one program's tile
_BLOCK_C = 64  # channels of one program's tile


@triton.jit
def _source(o, n):
    """(i0, i1, l) of output index o (int tensor) along an axis of n input pixels, resized to 2n."""
    s = tl.maximum(0.5 * (o.to(tl.float32) + 0.5) - 0.5, 0.0)
    i0 = s.to(tl.int32)
    i1 = i0 + tl.where(i0 < n - 1, 1, 0)
    return i0, i1, s - i0.to(tl.float32)


@triton.jit
def _upsample_forward_kernel(x_ptr, y_ptr, H, W, C, BLOCK_P: tl.constexpr, BLOCK_C: tl.constexpr):
    pt, ct, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    p = pt * BLOCK_P + tl.arange(0, BLOCK_P)  # output pixel (row-major over 2H x 2W)
    c = ct * BLOCK_C + tl.arange(0, BLOCK_C)
    pm = p < 4 * H * W
    mask = pm[:, None] & (c < C)[None, :]
    oy, ox = p // (2 * W), p % (2 * W)
    y0, y1, ly = _source(oy, H)
    x0, x1, lx = _source(ox, W)
    base = b.to(tl.int64) * H * W
    cc = c[None, :]
    v00 = tl.load(x_ptr + (base + y0 * W + x0)[:, None] * C + cc, mask=mask, other=0.0).to(tl.float32)
    v01 = tl.load(x_ptr + (base + y0 * W + x1)[:, None] * C + cc, mask=mask, other=0.0).to(tl.float32)
    v10 = tl.load(x_ptr + (base + y1 * W + x0)[:, None] * C + cc, mask=mask, other=0.0).to(tl.float32)
    v11 = tl.load(x_ptr + (base + y1 * W + x1)[:, None] * C + cc, mask=mask, other=0.0).to(tl.float32)
    wx1 = lx[:, None]
    wx0 = 1.0 - wx1
    wy1 = ly[:, None]
    out = (1.0 - wy1) * (wx0 * v00 + wx1 * v01) + wy1 * (wx0 * v10 + wx1 * v11)
    out_offs = (b.to(tl.int64) * 4 * H * W + p)[:, None] * C + cc
    tl.store(y_ptr + out_offs, out.to(y_ptr.dtype.element_ty), mask=mask)


@triton.jit
def _weight(o, i, n):
    """Weight with which output o (resized from n to 2n) reads input pixel i, and whether o exists."""
    valid = (o >= 0) & (o < 2 * n)
    i0, i1, l = _source(tl.maximum(o, 0), n)
    w = tl.where(i0 == i, 1.0 - l, 0.0) + tl.where(i1 == i, l, 0.0)
    return tl.where(valid, w, 0.0), valid


@triton.jit
def _upsample_backward_kernel(g_ptr, dx_ptr, H, W, C, BLOCK_P: tl.constexpr, BLOCK_C: tl.constexpr):
    pt, ct, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    p = pt * BLOCK_P + tl.arange(0, BLOCK_P)  # input pixel (row-major over H x W)
    c = ct * BLOCK_C + tl.arange(0, BLOCK_C)
    pm = p < H * W
    cm = (c < C)[None, :]
    iy, ix = p // W, p % W
    base = b.to(tl.int64) * 4 * H * W
    acc = tl.zeros((BLOCK_P, BLOCK_C), dtype=tl.float32)
    for dy in tl.static_range(4):
        oy = 2 * iy - 1 + dy
        wy, vy = _weight(oy, iy, H)
        for dx in tl.static_range(4):
            ox = 2 * ix - 1 + dx
            wx, vx = _weight(ox, ix, W)
            m = pm & vy & vx
            offs = (base + oy * 2 * W + ox)[:, None] * C + c[None, :]
            g = tl.load(g_ptr + offs, mask=m[:, None] & cm, other=0.0).to(tl.float32)
            acc += (wy * wx)[:, None] * g
    out_offs = (b.to(tl.int64) * H * W + p)[:, None] * C + c[None, :]
    tl.store(dx_ptr + out_offs, acc.to(dx_ptr.dtype.element_ty), mask=pm[:, None] & cm)


def _grid(pixels: int, C: int, B: int) -> tuple[int, int, int]:
    return triton.cdiv(pixels, _BLOCK_P), triton.cdiv(C, _BLOCK_C), B


def forward(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """x [B, C, H, W] channels-last -> [B, C, 2H, 2W] channels-last in ``dtype``."""
    B, C, H, W = x.shape
    y = torch.empty(B, C, 2 * H, 2 * W, device=x.device, dtype=dtype, memory_format=torch.channels_last)
    _upsample_forward_kernel[_grid(4 * H * W, C, B)](x, y, H, W, C, BLOCK_P=_BLOCK_P, BLOCK_C=_BLOCK_C)
    return y


def backward(grad: torch.Tensor, H: int, W: int, dtype: torch.dtype) -> torch.Tensor:
    """The input's gradient [B, C, H, W] (channels-last, ``dtype``) from the output's [B, C, 2H, 2W]."""
    B, C = grad.shape[:2]
    grad = grad.contiguous(memory_format=torch.channels_last)
    dx = torch.empty(B, C, H, W, device=grad.device, dtype=dtype, memory_format=torch.channels_last)
    _upsample_backward_kernel[_grid(H * W, C, B)](grad, dx, H, W, C, BLOCK_P=_BLOCK_P, BLOCK_C=_BLOCK_C)
    return dx
