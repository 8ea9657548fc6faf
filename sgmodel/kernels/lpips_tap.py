"""Triton kernels of LPIPS's tap distance and its gradient (``sgmodel.metrics.lpips.tap_distance``) for CUDA feature
maps in float32, float16 or bfloat16, of any strides.

Imported only on CUDA with Triton present; elsewhere ``lpips._TapDistance`` computes the same map with PyTorch
operations, which is also the float64 reference the kernels are tested against (tests/sgmodel/kernels/test_lpips_kernels.py).
Conventions as ``_TapDistance``'s: features a, b [N, C, h, w], the layer's linear weights w [C] (float32);
the map d [N, 1, h, w] = sum_c w_c (a_c / n_a - b_c / n_b)^2 with n_f = |f| + 1e-10, |f| the L2 norm over
channels.

Forward: one program per block of BP pixels, every channel of them at once (a [BP, BC] tile, BC = C rounded
up to a power of two): it reads a and b once, in their own strides, and writes d and the norms |a|, |b|
(float32, one per pixel: with the features, all the backward needs). PyTorch's operations made and re-read
float32 copies of the feature maps (the normalised difference, its square, their products): 128 x 64 x
256 x 256 at the first tap in a training step, about 47 ms of elementwise work forward and backward on an
H100 before these kernels.
Backward: the same tile; the normalised difference recomputed from the features and norms, h = w (u_a - u_b),
then for each side wanted g_f = +-2 grad (h - f (h . f) / (n_f |f|)) / n_f (+ for a, - for b; the second term
taken as 0 where |f| = 0, as ``_TapDistance``), written in the feature's dtype and strides. In float32
throughout, the channel sums in the tile's order.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

#: elements of a program's [pixels, channels] tile (pixels = this // channels rounded up to a power of two;
#: ``lpips._KERNEL_MAX_CHANNELS`` bounds the channels).
_TILE = 4096


@triton.jit
def _offsets(pix, HW, W, sn, sh, sw):
    """The element offsets of pixels ``pix`` (flat over N, h, w) in a tensor of strides (sn, ., sh, sw)."""
    p = pix.to(tl.int64)
    n, r = p // HW, p % HW
    return n * sn + (r // W) * sh + (r % W) * sw


@triton.jit
def _load(ptr, pix, ch, m, HW, W, sn, sc, sh, sw):
    """The [BP, BC] tile of a feature map, float32 (0 outside the mask)."""
    offs = _offsets(pix, HW, W, sn, sh, sw)[:, None] + (ch.to(tl.int64) * sc)[None, :]
    return tl.load(ptr + offs, mask=m, other=0.0).to(tl.float32)


@triton.jit
def _tile(a_ptr, b_ptr, w_ptr, P, C, HW, W, san, sac, sah, saw, sbn, sbc, sbh, sbw,
          BP: tl.constexpr, BC: tl.constexpr):
    """This program's pixels, channels, their masks, the [BP, BC] tiles of a and b (float32) and the weights."""
    pix = tl.program_id(0) * BP + tl.arange(0, BP)
    ch = tl.arange(0, BC)
    pok = pix < P
    m = pok[:, None] & (ch < C)[None, :]
    a = _load(a_ptr, pix, ch, m, HW, W, san, sac, sah, saw)
    b = _load(b_ptr, pix, ch, m, HW, W, sbn, sbc, sbh, sbw)
    w = tl.load(w_ptr + ch, mask=ch < C, other=0.0)
    return pix, ch, pok, m, a, b, w


@triton.jit
def _tap_forward_kernel(a_ptr, b_ptr, w_ptr, d_ptr, na_ptr, nb_ptr, P, C, HW, W,
                        san, sac, sah, saw, sbn, sbc, sbh, sbw, eps, BP: tl.constexpr, BC: tl.constexpr):
    pix, ch, pok, m, a, b, w = _tile(a_ptr, b_ptr, w_ptr, P, C, HW, W, san, sac, sah, saw, sbn, sbc, sbh, sbw, BP, BC)
    na = tl.sqrt(tl.sum(a * a, axis=1))
    nb = tl.sqrt(tl.sum(b * b, axis=1))
    diff = a / (na + eps)[:, None] - b / (nb + eps)[:, None]
    d = tl.sum(w[None, :] * diff * diff, axis=1)
    tl.store(d_ptr + pix, d, mask=pok)
    tl.store(na_ptr + pix, na, mask=pok)
    tl.store(nb_ptr + pix, nb, mask=pok)


@triton.jit
def _side_gradient(f, h, norm, eps, scale):
    """(h - f (h . f) / ((|f| + eps) |f|)) * scale / (|f| + eps), the second term 0 where |f| = 0."""
    n = norm + eps
    along = tl.sum(h * f, axis=1) / (n * tl.where(norm > 0, norm, 1.0))
    return (h - f * along[:, None]) * (scale / n)[:, None]


@triton.jit
def _tap_backward_kernel(g_ptr, a_ptr, b_ptr, w_ptr, na_ptr, nb_ptr, da_ptr, db_ptr, P, C, HW, W,
                         sgn, sgh, sgw, san, sac, sah, saw, sbn, sbc, sbh, sbw,
                         sdan, sdac, sdah, sdaw, sdbn, sdbc, sdbh, sdbw, eps,
                         NEED_A: tl.constexpr, NEED_B: tl.constexpr, BP: tl.constexpr, BC: tl.constexpr):
    pix, ch, pok, m, a, b, w = _tile(a_ptr, b_ptr, w_ptr, P, C, HW, W, san, sac, sah, saw, sbn, sbc, sbh, sbw, BP, BC)
    na = tl.load(na_ptr + pix, mask=pok, other=0.0)
    nb = tl.load(nb_ptr + pix, mask=pok, other=0.0)
    grad = tl.load(g_ptr + _offsets(pix, HW, W, sgn, sgh, sgw), mask=pok, other=0.0).to(tl.float32)
    h = w[None, :] * (a / (na + eps)[:, None] - b / (nb + eps)[:, None])
    ch64 = ch.to(tl.int64)[None, :]
    if NEED_A:
        ga = _side_gradient(a, h, na, eps, 2.0 * grad)
        offs = _offsets(pix, HW, W, sdan, sdah, sdaw)[:, None] + ch64 * sdac
        tl.store(da_ptr + offs, ga.to(da_ptr.dtype.element_ty), mask=m)
    if NEED_B:
        gb = _side_gradient(b, h, nb, eps, -2.0 * grad)
        offs = _offsets(pix, HW, W, sdbn, sdbh, sdbw)[:, None] + ch64 * sdbc
        tl.store(db_ptr + offs, gb.to(db_ptr.dtype.element_ty), mask=m)


def _tile_shape(c: int) -> tuple[int, int]:
    """(BP, BC): the tile's pixels and channels for C channels."""
    bc = triton.next_power_of_2(c)
    return max(1, _TILE // bc), bc


def forward(a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor, eps: float
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The map d [N, 1, h, w] (float32) and the norms |a|, |b| [N, 1, h, w] (float32) of features a, b
    [N, C, h, w] (one dtype, any strides) with weights [C] (float32, contiguous)."""
    n, c, h, w = a.shape
    d, na, nb = (torch.empty((n, 1, h, w), device=a.device, dtype=torch.float32) for _ in range(3))
    bp, bc = _tile_shape(c)
    grid = (triton.cdiv(n * h * w, bp),)
    _tap_forward_kernel[grid](a, b, weight, d, na, nb, n * h * w, c, h * w, w, *a.stride(), *b.stride(), eps,
                              BP=bp, BC=bc, num_warps=4)
    return d, na, nb


def backward(grad: torch.Tensor, a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor, na: torch.Tensor,
             nb: torch.Tensor, eps: float, need_a: bool, need_b: bool
             ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The gradients of a and b wanted (each in its feature's dtype and memory format) from the gradient of
    the map ``grad`` [N, 1, h, w] (any strides, an expanded one included)."""
    n, c, h, w = a.shape
    da = torch.empty_like(a) if need_a else None
    db = torch.empty_like(b) if need_b else None
    bp, bc = _tile_shape(c)
    grid = (triton.cdiv(n * h * w, bp),)
    sg = grad.stride()
    da_or_a, db_or_b = a if da is None else da, b if db is None else db  # an unwanted side's pointer is unused
    _tap_backward_kernel[grid](grad, a, b, weight, na, nb, da_or_a, db_or_b, n * h * w, c, h * w, w,
                               sg[0], sg[2], sg[3], *a.stride(), *b.stride(), *da_or_a.stride(), *db_or_b.stride(),
                               eps, NEED_A=need_a, NEED_B=need_b, BP=bp, BC=bc, num_warps=4)
    return da, db
