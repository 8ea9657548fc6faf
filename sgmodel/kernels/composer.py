"""Triton kernels of the composer's attributes (``sgmodel.model.composer.compose``, the paper's model: the
composer on, no edge gate), forward and backward, one pass each per layer.

Imported only on CUDA with Triton present; ``composer.compose``'s PyTorch path runs everywhere else, and that path
(itself tested against the float64 reference of appendix A) is what the kernels are tested against
(tests/sgmodel/kernels/test_composer_kernels.py). Why: in PyTorch the attributes are some 60 elementwise operations
over [B, 37, Hc, Wc] float32 copies of the branches, each a pass through memory, and as many again backward (about
7 ms forward at the paper's batch of 32 on an H100). Here a program reads a block of pixels' 37 branch channels once
(in the branch's dtype and strides, a bf16 channels-last view included), computes every attribute in float32
registers and writes them to their rows of the outputs (an SH row of 27 floats and a quaternion in one store each:
separate stores 108 bytes apart made the forward slower than PyTorch's); the backward recomputes what it needs from
the branch and writes the branch's gradient in its dtype, and the depth's. Floating-point contraction is off, so
every multiply and add rounds as PyTorch's separate operations do. 3.2 against 7.3 ms forward on an H100 at the
paper's batch (docs/benchmarks.md "Issue 37: the composer in two kernels").

Per pixel (u the column, v the row, z_l the layer's depth in metres; ``composer``'s docstring):
means = z_l K~^-1 (u + 1/2 + sigmoid(o_u) - 1/2, v + 1/2 + sigmoid(o_v) - 1/2, 1); quats = normalise((1, 0,
0, 0) + R_QUAT dq) (the identity below a norm of 1e-12); scales = clip(s0 phi(min(ds, cap)), S_MIN, S_MAX),
s0 = KAPPA z_l / sqrt(fx fy), cap from the front layer's edge band or the back layer's constant; opacity =
sigmoid(logit(ALPHA0) + da); SH DC = (RGB~ - 1/2) / C0 + dc_0, degree j: 0.1 0.25^j dc_j. Gradients as
PyTorch's: a clip passes it where min <= x <= max, ``minimum`` halves it on a tie.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

_BLOCK = 256  # pixels of one program


@triton.jit
def _sigmoid(x):
    return 1.0 / (1.0 + tl.exp(-x))


@triton.jit
def _pixels(HW, W, BLOCK: tl.constexpr):
    """(pixel indices p of this program's block, mask, row v, column u as float32, image b)."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    return p, p < HW, (p // W).to(tl.float32), (p % W).to(tl.float32), tl.program_id(1)


@triton.jit
def _ray(kinv_ptr, b, u, v, du, dv):
    """The ray K~^-1 [u + 1/2 + du, v + 1/2 + dv, 1] of image b's pixels: (x, y, z)."""
    px, py = (u + 0.5) + du, (v + 0.5) + dv
    k = kinv_ptr + b * 9
    return (tl.load(k) * px + tl.load(k + 1) * py + tl.load(k + 2),
            tl.load(k + 3) * px + tl.load(k + 4) * py + tl.load(k + 5),
            tl.load(k + 6) * px + tl.load(k + 7) * py + tl.load(k + 8))


@triton.jit
def _quat(src, sc, m, R_QUAT: tl.constexpr):
    """The quaternion (1, 0, 0, 0) + R_QUAT dq of the branch's channels 6 to 9 at ``src``, and its squared norm
    (summed left to right, as PyTorch's): (q0, q1, q2, q3, |q|^2), float32."""
    q0 = 1.0 + R_QUAT * tl.load(src + 6 * sc, mask=m, other=0.0).to(tl.float32)
    q1 = R_QUAT * tl.load(src + 7 * sc, mask=m, other=0.0).to(tl.float32)
    q2 = R_QUAT * tl.load(src + 8 * sc, mask=m, other=0.0).to(tl.float32)
    q3 = R_QUAT * tl.load(src + 9 * sc, mask=m, other=0.0).to(tl.float32)
    return q0, q1, q2, q3, ((q0 * q0 + q1 * q1) + q2 * q2) + q3 * q3


@triton.jit
def _cap(band_ptr, b, HW, p, m, cap_edge, cap_all, HAS_BAND: tl.constexpr):
    """The scale residuals' cap at the block's pixels: ``cap_edge`` in the edge band (when the layer has one),
    ``cap_all`` elsewhere."""
    cap = cap_all
    if HAS_BAND:
        cap = tl.where(tl.load(band_ptr + b.to(tl.int64) * HW + p, mask=m, other=0) != 0, cap_edge, cap_all)
    return cap


@triton.jit
def _forward_kernel(br_ptr, sb, sc, sh, sw, z_ptr, rgb_ptr, rgb_sb, rgb_sc, band_ptr, kinv_ptr, rs_ptr,
                    means_ptr, quats_ptr, scales_ptr, opac_ptr, sh_ptr, HW, W, N, row0,
                    cap_edge, cap_all, S_MIN: tl.constexpr, S_MAX: tl.constexpr, KAPPA: tl.constexpr,
                    R_QUAT: tl.constexpr, EPS2: tl.constexpr, LOGIT: tl.constexpr, C0: tl.constexpr,
                    PHI_RANGE: tl.constexpr, PHI_MIN: tl.constexpr, PHI_SLOPE: tl.constexpr, PHI_SHIFT: tl.constexpr,
                    DECAY1: tl.constexpr, DECAY2: tl.constexpr, HAS_BAND: tl.constexpr, BLOCK: tl.constexpr):
    p, m, v, u, b = _pixels(HW, W, BLOCK)
    src = br_ptr + b.to(tl.int64) * sb + (p // W).to(tl.int64) * sh + (p % W).to(tl.int64) * sw
    z = tl.load(z_ptr + b.to(tl.int64) * HW + p, mask=m, other=1.0)
    row = b.to(tl.int64) * N + row0 + p
    # centres
    du = _sigmoid(tl.load(src + 1 * sc, mask=m, other=0.0).to(tl.float32)) - 0.5
    dv = _sigmoid(tl.load(src + 2 * sc, mask=m, other=0.0).to(tl.float32)) - 0.5
    rx, ry, rz = _ray(kinv_ptr, b, u, v, du, dv)
    tl.store(means_ptr + row * 3, z * rx, mask=m)
    tl.store(means_ptr + row * 3 + 1, z * ry, mask=m)
    tl.store(means_ptr + row * 3 + 2, z * rz, mask=m)
    # rotations
    q0, q1, q2, q3, n2 = _quat(src, sc, m, R_QUAT)
    ok = n2 > EPS2
    norm = tl.sqrt(tl.maximum(n2, EPS2))
    q = tl.join(tl.join(tl.where(ok, q0 / norm, 1.0), tl.where(ok, q2 / norm, 0.0)),  # [p, i, j]: component 2i + j
                tl.join(tl.where(ok, q1 / norm, 0.0), tl.where(ok, q3 / norm, 0.0))).reshape(BLOCK, 4)
    tl.store(quats_ptr + row[:, None] * 4 + tl.arange(0, 4)[None, :], q, mask=m[:, None])
    # scales
    s0 = KAPPA * z / tl.load(rs_ptr + b)
    cap = _cap(band_ptr, b, HW, p, m, cap_edge, cap_all, HAS_BAND)
    for i in tl.static_range(3):
        t = tl.minimum(tl.load(src + (3 + i) * sc, mask=m, other=0.0).to(tl.float32), cap)
        s = s0 * (PHI_RANGE * _sigmoid(PHI_SLOPE * t + PHI_SHIFT) + PHI_MIN)
        tl.store(scales_ptr + row * 3 + i, tl.minimum(tl.maximum(s, S_MIN), S_MAX), mask=m)
    # opacity and colour
    tl.store(opac_ptr + row, _sigmoid(tl.load(src, mask=m, other=0.0).to(tl.float32) + LOGIT), mask=m)
    # colour: one tile of the 27 coefficients, rows of the output written whole
    k = tl.arange(0, 32)
    tile = m[:, None] & (k < 27)[None, :]
    x = tl.load(src[:, None] + (10 + k)[None, :] * sc, mask=tile, other=0.0).to(tl.float32)
    rgb = tl.load(rgb_ptr + b.to(tl.int64) * rgb_sb + p[:, None] + k[None, :] * rgb_sc,
                  mask=m[:, None] & (k < 3)[None, :], other=0.5)
    tl.store(sh_ptr + row[:, None] * 27 + k[None, :], _sh_base(k, rgb, C0) + _decay(k, DECAY1, DECAY2) * x,
             mask=tile)


@triton.jit
def _decay(k, DECAY1: tl.constexpr, DECAY2: tl.constexpr):
    """The residual's factor of SH output column k (coefficient k // 3: 1 for the DC term, 0.1 x 0.25^j for a
    coefficient of degree j: 1 to 3 of degree 1, 4 to 8 of degree 2)."""
    return tl.where(k < 3, 1.0, tl.where(k < 12, DECAY1, DECAY2))[None, :]


@triton.jit
def _sh_base(k, rgb, C0: tl.constexpr):
    """The DC term's base (RGB~ - 1/2) / C0 in columns 0 to 2, zero beyond."""
    return tl.where((k < 3)[None, :], (rgb - 0.5) / C0, 0.0)


@triton.jit
def _backward_kernel(br_ptr, sb, sc, sh, sw, d_ptr, dsb, dsc, dsh, dsw, z_ptr, dz_ptr, band_ptr, kinv_ptr,
                     rs_ptr, g_means, g_quats, g_scales, g_opac, g_sh, HW, W, N, row0, cap_edge, cap_all,
                     S_MIN: tl.constexpr, S_MAX: tl.constexpr, KAPPA: tl.constexpr, R_QUAT: tl.constexpr,
                     EPS2: tl.constexpr, LOGIT: tl.constexpr, C0: tl.constexpr, PHI_RANGE: tl.constexpr,
                     PHI_MIN: tl.constexpr, PHI_SLOPE: tl.constexpr, PHI_SHIFT: tl.constexpr, DECAY1: tl.constexpr,
                     DECAY2: tl.constexpr, HAS_BAND: tl.constexpr, WANT_DZ: tl.constexpr, BLOCK: tl.constexpr):
    p, m, v, u, b = _pixels(HW, W, BLOCK)
    pix = (p // W).to(tl.int64), (p % W).to(tl.int64)
    src = br_ptr + b.to(tl.int64) * sb + pix[0] * sh + pix[1] * sw
    dst = d_ptr + b.to(tl.int64) * dsb + pix[0] * dsh + pix[1] * dsw
    ty = d_ptr.dtype.element_ty
    z = tl.load(z_ptr + b.to(tl.int64) * HW + p, mask=m, other=1.0)
    row = b.to(tl.int64) * N + row0 + p
    # centres: means = z r, r = K^-1 pix
    su = _sigmoid(tl.load(src + 1 * sc, mask=m, other=0.0).to(tl.float32))
    sv = _sigmoid(tl.load(src + 2 * sc, mask=m, other=0.0).to(tl.float32))
    rx, ry, rz = _ray(kinv_ptr, b, u, v, su - 0.5, sv - 0.5)
    gx = tl.load(g_means + row * 3, mask=m, other=0.0)
    gy = tl.load(g_means + row * 3 + 1, mask=m, other=0.0)
    gz = tl.load(g_means + row * 3 + 2, mask=m, other=0.0)
    dz = (rx * gx + ry * gy) + rz * gz
    k = kinv_ptr + b * 9
    dpx = z * ((tl.load(k) * gx + tl.load(k + 3) * gy) + tl.load(k + 6) * gz)
    dpy = z * ((tl.load(k + 1) * gx + tl.load(k + 4) * gy) + tl.load(k + 7) * gz)
    tl.store(dst + 1 * dsc, (dpx * (su * (1.0 - su))).to(ty), mask=m)
    tl.store(dst + 2 * dsc, (dpy * (sv * (1.0 - sv))).to(ty), mask=m)
    # rotations: d q = (g - unit (unit . g)) / |q| where |q|^2 > EPS2, else nothing
    q0, q1, q2, q3, n2 = _quat(src, sc, m, R_QUAT)
    norm = tl.sqrt(tl.maximum(n2, EPS2))
    scale = tl.where(n2 > EPS2, R_QUAT / norm, 0.0)
    g0 = tl.load(g_quats + row * 4, mask=m, other=0.0)
    g1 = tl.load(g_quats + row * 4 + 1, mask=m, other=0.0)
    g2 = tl.load(g_quats + row * 4 + 2, mask=m, other=0.0)
    g3 = tl.load(g_quats + row * 4 + 3, mask=m, other=0.0)
    dot = (((q0 * g0 + q1 * g1) + q2 * g2) + q3 * g3) / (norm * norm)
    tl.store(dst + 6 * dsc, (scale * (g0 - q0 * dot)).to(ty), mask=m)
    tl.store(dst + 7 * dsc, (scale * (g1 - q1 * dot)).to(ty), mask=m)
    tl.store(dst + 8 * dsc, (scale * (g2 - q2 * dot)).to(ty), mask=m)
    tl.store(dst + 9 * dsc, (scale * (g3 - q3 * dot)).to(ty), mask=m)
    # scales
    rs = tl.load(rs_ptr + b)
    s0 = KAPPA * z / rs
    cap = _cap(band_ptr, b, HW, p, m, cap_edge, cap_all, HAS_BAND)
    ds0 = tl.zeros_like(z)
    for i in tl.static_range(3):
        x = tl.load(src + (3 + i) * sc, mask=m, other=0.0).to(tl.float32)
        t = tl.minimum(x, cap)
        sg = _sigmoid(PHI_SLOPE * t + PHI_SHIFT)
        ph = PHI_RANGE * sg + PHI_MIN
        s = s0 * ph
        g = tl.load(g_scales + row * 3 + i, mask=m, other=0.0)
        g = tl.where((s >= S_MIN) & (s <= S_MAX), g, 0.0)
        ds0 += g * ph
        share = tl.where(x < cap, 1.0, tl.where(x == cap, 0.5, 0.0))
        tl.store(dst + (3 + i) * dsc, (g * s0 * (PHI_RANGE * PHI_SLOPE * (sg * (1.0 - sg))) * share).to(ty), mask=m)
    dz += ds0 * (KAPPA / rs)
    if WANT_DZ:
        tl.store(dz_ptr + b.to(tl.int64) * HW + p, dz, mask=m)
    # opacity and colour
    a = _sigmoid(tl.load(src, mask=m, other=0.0).to(tl.float32) + LOGIT)
    tl.store(dst, (tl.load(g_opac + row, mask=m, other=0.0) * (a * (1.0 - a))).to(ty), mask=m)
    k = tl.arange(0, 32)
    tile = m[:, None] & (k < 27)[None, :]
    g = tl.load(g_sh + row[:, None] * 27 + k[None, :], mask=tile, other=0.0)
    tl.store(dst[:, None] + (10 + k)[None, :] * dsc, (_decay(k, DECAY1, DECAY2) * g).to(ty), mask=tile)


def forward(branches: list[torch.Tensor], depths: list[torch.Tensor], rgb: torch.Tensor, kinv: torch.Tensor,
            rs: torch.Tensor, band: torch.Tensor, caps: list[tuple[float, float, bool]], constants: dict) -> tuple:
    """The attributes (means [B,N,3], quats [B,N,4], scales [B,N,3], opacities [B,N], sh [B,N,9,3], float32) of
    the layers' ``branches`` [B,37,H,W] (any float dtype and strides) on their ``depths`` [B,1,H,W] float32
    contiguous; rgb [B,3,H,W] float32 contiguous, kinv [B,3,3] float32, rs [B] = sqrt(fx fy), band [B,1,H,W]
    uint8, caps per layer (cap in the band, cap elsewhere, whether the band applies); ``constants``: the
    composer's (``composer.KERNEL_CONSTANTS``). Layer i's Gaussians are rows i H W to (i + 1) H W."""
    B, _, H, W = branches[0].shape
    HW, dev = H * W, branches[0].device
    N = HW * len(branches)
    out = (torch.empty(B, N, 3, device=dev), torch.empty(B, N, 4, device=dev), torch.empty(B, N, 3, device=dev),
           torch.empty(B, N, device=dev), torch.empty(B, N, 9, 3, device=dev))
    for i, (br, d, (cap_edge, cap_all, has_band)) in enumerate(zip(branches, depths, caps)):
        _forward_kernel[(triton.cdiv(HW, _BLOCK), B)](
            br, *br.stride(), d, rgb, rgb.stride(0), rgb.stride(1), band, kinv, rs, *out, HW, W, N, i * HW,
            cap_edge, cap_all, HAS_BAND=has_band, BLOCK=_BLOCK, enable_fp_fusion=False, **constants)
    return out


def backward(grads: tuple, branches: list[torch.Tensor], depths: list[torch.Tensor], want_depth: list[bool],
             kinv: torch.Tensor, rs: torch.Tensor, band: torch.Tensor, caps: list[tuple[float, float, bool]],
             constants: dict) -> tuple[list[torch.Tensor], list[torch.Tensor | None]]:
    """(each branch's gradient, in its dtype and channels-last; each depth's gradient [B,1,H,W] float32 where
    ``want_depth``, else None) from the gradients of ``forward``'s outputs (contiguous float32)."""
    B, _, H, W = branches[0].shape
    HW, N = H * W, H * W * len(branches)
    d_branches, d_depths = [], []
    for i, (br, d, (cap_edge, cap_all, has_band)) in enumerate(zip(branches, depths, caps)):
        d_br = torch.empty(br.shape, dtype=br.dtype, device=br.device, memory_format=torch.channels_last)
        d_d = torch.empty_like(d) if want_depth[i] else None
        _backward_kernel[(triton.cdiv(HW, _BLOCK), B)](
            br, *br.stride(), d_br, *d_br.stride(), d, d if d_d is None else d_d, band, kinv, rs, *grads, HW, W, N,
            i * HW, cap_edge, cap_all, HAS_BAND=has_band, WANT_DZ=want_depth[i], BLOCK=_BLOCK,
            enable_fp_fusion=False, **constants)
        d_branches.append(d_br)
        d_depths.append(d_d)
    return d_branches, d_depths
