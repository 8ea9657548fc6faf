"""Triton kernels of the channel concatenation with edge replication (``sgmodel.model.layers.cat_channels``): the
predictor's inputs written onto the canvas in one pass.

Imported only on CUDA with Triton present; elsewhere ``cat_channels`` pads with ``layers.replicate_pad`` and
concatenates with ``torch.cat``, the reference the kernels are tested against (tests/sgmodel/kernels/test_concat_kernels.py).

Forward: the output [B, Ctot, Hd, Wd] is channels-last. Each program writes every channel of a tile of
output pixels, chunk by chunk; an output channel is read from the source that owns it at the pixel
(clamp(y - P_k, 0, H_k - 1), clamp(x - P_k, 0, W_k - 1)) — edge replication by the source's P_k pixels — or
is the constant of the appended channels (the first one, the rest zero). Sources come in any strides (no
copies first), up to three, in the output's dtype. PyTorch's concatenation of channels-last tensors copies
each source into its channel slice in a pass of its own (a few bytes of every pixel at a time for the
RGB and depth), after a padded copy of each source.

Backward, per source that needs it: its gradient gathered from the output's. A source pixel receives its
own output pixel and, on the border, the P padded rows and columns (corner blocks included) that copied it,
summed in float32 (float64 for float64 sources) and written once, channels-last in the source's dtype.

A source may come with a bias (one number per channel, added in float32, float64 for float64 sources, as the
values are copied: a convolution's bias, which the convolution then need not add in a pass of its own). Its
gradient is the channel's sum over every output pixel, which is the sum of what the backward writes for the
source: each program also writes its own channel sums (one row of a small table in the sums' precision), and
the rows are added up.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from sgmodel.kernels import CAT_KERNEL_SOURCES

_BLOCK_P = 32  # output pixels of one forward program
_BLOCK_C = 64  # channels of one chunk
_BLOCK_X = 32  # source pixels (along a row) of one backward program


@triton.jit
def _read(src_ptr, bias_ptr, b, oy, ox, pm, c, lo, C, P, H, W, sb, sc, sy, sx, BIAS: tl.constexpr):
    """The values of output channels ``c`` that a source owns ([lo, lo + C)) at output pixels (oy, ox) of
    image b, edge-replicated by P pixels, plus the source's bias where it has one (added in float32, float64 for
    a float64 source), and where they are owned."""
    own = (c >= lo) & (c < lo + C)
    iy = tl.minimum(tl.maximum(oy - P, 0), H - 1).to(tl.int64)
    ix = tl.minimum(tl.maximum(ox - P, 0), W - 1).to(tl.int64)
    offs = b * sb + (iy * sy + ix * sx)[:, None] + ((c - lo).to(tl.int64) * sc)[None, :]
    m = pm[:, None] & own[None, :]
    v = tl.load(src_ptr + offs, mask=m, other=0.0)
    if BIAS:
        acc = tl.float64 if src_ptr.dtype.element_ty == tl.float64 else tl.float32
        v = v.to(acc) + tl.load(bias_ptr + (c - lo), mask=own, other=0.0).to(acc)[None, :]
    return v, m


@triton.jit
def _concat_kernel(out_ptr, s0, s1, s2, b0, b1, b2, Hd, Wd, Ctot, used,
                   lo0, C0, P0, H0, W0, sb0, sc0, sy0, sx0,
                   lo1, C1, P1, H1, W1, sb1, sc1, sy1, sx1,
                   lo2, C2, P2, H2, W2, sb2, sc2, sy2, sx2,
                   BIAS0: tl.constexpr, BIAS1: tl.constexpr, BIAS2: tl.constexpr,
                   BLOCK_P: tl.constexpr, BLOCK_C: tl.constexpr):
    pt, b = tl.program_id(0), tl.program_id(1).to(tl.int64)
    p = pt * BLOCK_P + tl.arange(0, BLOCK_P)
    pm = p < Hd * Wd
    oy, ox = p // Wd, p % Wd
    dtype = out_ptr.dtype.element_ty
    rows = (b * Hd * Wd + p.to(tl.int64)) * Ctot
    for c0 in range(0, Ctot, BLOCK_C):
        c = c0 + tl.arange(0, BLOCK_C)
        v = tl.broadcast_to(tl.where(c == used, 1.0, 0.0)[None, :], (BLOCK_P, BLOCK_C)).to(dtype)
        v0, m0 = _read(s0, b0, b, oy, ox, pm, c, lo0, C0, P0, H0, W0, sb0, sc0, sy0, sx0, BIAS0)
        v = tl.where(m0, v0.to(dtype), v)
        v1, m1 = _read(s1, b1, b, oy, ox, pm, c, lo1, C1, P1, H1, W1, sb1, sc1, sy1, sx1, BIAS1)
        v = tl.where(m1, v1.to(dtype), v)
        v2, m2 = _read(s2, b2, b, oy, ox, pm, c, lo2, C2, P2, H2, W2, sb2, sc2, sy2, sx2, BIAS2)
        v = tl.where(m2, v2.to(dtype), v)
        tl.store(out_ptr + rows[:, None] + c[None, :], v, mask=pm[:, None] & (c < Ctot)[None, :])


@triton.jit
def _concat_backward_kernel(g_ptr, dx_ptr, sums_ptr, Hd, Wd, Ctot, lo, C, P, H, W,
                            BLOCK_X: tl.constexpr, BLOCK_C: tl.constexpr, ACC: tl.constexpr, SUMS: tl.constexpr):
    n_xt = tl.cdiv(W, BLOCK_X)
    xt, ct = tl.program_id(0) % n_xt, tl.program_id(0) // n_xt
    iy, b = tl.program_id(1), tl.program_id(2).to(tl.int64)
    ix = xt * BLOCK_X + tl.arange(0, BLOCK_X)
    c = ct * BLOCK_C + tl.arange(0, BLOCK_C)
    cm = c < C
    m = (ix < W)[:, None] & cm[None, :]
    chan = lo + c
    # the output rows that copied source row iy: its own, and all the padded rows beyond a border row
    r0 = tl.where(iy == 0, 0, iy + P)
    r1 = tl.where(iy == H - 1, Hd - 1, iy + P)
    acc = tl.zeros((BLOCK_X, BLOCK_C), dtype=ACC)
    for r in range(r0, r1 + 1):
        row = (b * Hd + r) * Wd
        offs = (row + (ix + P).to(tl.int64))[:, None] * Ctot + chan[None, :]
        acc += tl.load(g_ptr + offs, mask=m, other=0.0).to(ACC)
        if xt == 0:  # the padded columns left of the border column
            for k in range(0, P):
                g = tl.load(g_ptr + (row + k) * Ctot + chan, mask=cm, other=0.0).to(ACC)
                acc += tl.where((ix == 0)[:, None], g[None, :], 0.0)
        if xt == n_xt - 1:  # and right of it
            for k in range(W + P, Wd):
                g = tl.load(g_ptr + (row + k) * Ctot + chan, mask=cm, other=0.0).to(ACC)
                acc += tl.where((ix == W - 1)[:, None], g[None, :], 0.0)
    out = ((b * H + iy) * W + ix.to(tl.int64))[:, None] * C + c[None, :]
    tl.store(dx_ptr + out, acc.to(dx_ptr.dtype.element_ty), mask=m)
    if SUMS:  # this program's share of the source's channel sums (its bias's gradient), one row per (b, iy, xt)
        tl.store(sums_ptr + ((b * H + iy) * n_xt + xt) * C + c, tl.sum(acc, axis=0), mask=cm)


def forward(tensors: list[torch.Tensor], pads: list[int], total: int,
            biases: list[torch.Tensor | None] | None = None) -> torch.Tensor:
    """``tensors`` [B, C_k, H_k, W_k] (at most three, one dtype, any strides), each edge-replicated by
    ``pads[k]`` to one size Hd x Wd, plus ``biases[k]`` [C_k] where given (``_read``), concatenated along
    channels and followed by ``total - sum C_k`` appended channels (the first ones, the rest zero) -> [B, total,
    Hd, Wd] channels-last."""
    if len(tensors) > CAT_KERNEL_SOURCES:
        raise ValueError(f"kernels.concat.forward reads at most {CAT_KERNEL_SOURCES} sources, got {len(tensors)}")
    biases = [None] * len(tensors) if biases is None else list(biases)
    x = tensors[0]
    B, Hd, Wd = x.shape[0], x.shape[2] + 2 * pads[0], x.shape[3] + 2 * pads[0]
    out = torch.empty(B, total, Hd, Wd, device=x.device, dtype=x.dtype, memory_format=torch.channels_last)
    args, lo = [], 0
    for t, p in zip(tensors, pads):
        sb, sc, sy, sx = t.stride()
        args += [lo, t.shape[1], p, t.shape[2], t.shape[3], sb, sc, sy, sx]
        lo += t.shape[1]
    unused = [lo, 0, 0, 1, 1, 0, 0, 0, 0]  # owns no channel
    for _ in range(CAT_KERNEL_SOURCES - len(tensors)):
        args += unused
    srcs = list(tensors) + [out] * (CAT_KERNEL_SOURCES - len(tensors))
    bias_args = [out if b is None else b.contiguous() for b in biases] + [out] * (CAT_KERNEL_SOURCES - len(tensors))
    flags = {f"BIAS{k}": k < len(biases) and biases[k] is not None for k in range(CAT_KERNEL_SOURCES)}
    _concat_kernel[(triton.cdiv(Hd * Wd, _BLOCK_P), B)](out, *srcs, *bias_args, Hd, Wd, total, lo, *args, **flags,
                                                         BLOCK_P=_BLOCK_P, BLOCK_C=_BLOCK_C)
    return out


def backward(grad: torch.Tensor, lo: int, channels: int, pad: int, height: int, width: int,
             dtype: torch.dtype, bias_dtype: torch.dtype | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(the gradient [B, channels, height, width] (channels-last, ``dtype``) of the source that owns output
    channels [lo, lo + channels), edge-replicated by ``pad``, from the output's gradient ``grad``; with
    ``bias_dtype``, its bias's gradient [channels] in that dtype: the sums over every output pixel, taken from
    the programs' sums of what they write, else None)."""
    B, Ctot, Hd, Wd = grad.shape
    grad = grad.contiguous(memory_format=torch.channels_last)
    dx = torch.empty(B, channels, height, width, device=grad.device, dtype=dtype, memory_format=torch.channels_last)
    acc = torch.float64 if dtype == torch.float64 else torch.float32
    x_tiles = triton.cdiv(width, _BLOCK_X)
    sums = torch.empty(B * height * x_tiles if bias_dtype else 1, channels, device=grad.device, dtype=acc)
    grid = (x_tiles * triton.cdiv(channels, _BLOCK_C), height, B)
    _concat_backward_kernel[grid](grad, dx, sums, Hd, Wd, Ctot, lo, channels, pad, height, width,
                                  BLOCK_X=_BLOCK_X, BLOCK_C=_BLOCK_C,
                                  ACC=tl.float64 if acc == torch.float64 else tl.float32, SUMS=bias_dtype is not None)
    return dx, None if bias_dtype is None else sums.sum(0).to(bias_dtype)
