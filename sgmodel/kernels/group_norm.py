"""Triton kernels of the fused GroupNorm (+ GELU) on channels-last tensors (``sgmodel.model.layers.group_norm_gelu``).

Imported only on CUDA with Triton present; ``layers.group_norm_gelu`` runs PyTorch's own operations
everywhere else, and that path is the reference the kernels are tested against (tests/sgmodel/model/test_layers.py).

A channels-last tensor [B, C, H, W] is the row-major array [B, P, C] (P = H W pixels), so a group (G
contiguous blocks of C / G channels) is a strided [P, C / G] slab of each image. Each kernel program reads
one group of one tile of ``block`` pixels (grid: group fastest, so that the programs reading one tile's
cache lines run together):

- forward: per tile, the group's sum and the sum of squared deviations from the tile's own mean, combined
  over tiles with Chan's parallel formula (``_combine``; no catastrophic cancellation of E[x^2] - E[x]^2);
  then y = act((x - mean) rstd gamma + beta) in one pass. Statistics in float32, as PyTorch's CUDA GroupNorm.
- backward, with g = dL/dx^ = dL/da gamma (a the GroupNorm output, dL/da = dL/dy act'(a)):
  dx = rstd (g - mean(g) - x^ mean(g x^)) per group and image, dgamma = sum dL/da x^, dbeta = sum dL/da;
  one pass for the sums (each program's over ``SUMS_ITERS`` tiles, the programs' added up here), one for dx. a is
  recomputed from x, never stored.

act is the exact (erf) GELU, 0.5 a (1 + erf(a / sqrt 2)), or the identity.

``parts`` > 1 (at most 3: the predictor's branches) splits the channels into equal blocks, each of which
is read by its own consumer: y is written, and dL/dy read, as ``parts`` separate channels-last tensors
[B, C / parts, H, W] (one buffer [parts, B, H, W, C / parts] forward), so that no consumer copies its
channel slice out of y and no concatenation assembles dL/dy from theirs. Groups never straddle two parts.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

#: (pixels x channels of one program's tile, warps of a program) of the forward's kernels (statistics, apply) and
#: of the backward's (sums, dx); any tile of at least 16 pixels computes the same function up to float32 summation
#: order. ``python scripts/profile/gpu_group_norm_tiles.py`` times the choices (docs/benchmarks.md).
FORWARD_LAUNCH = (2048, 2)
BACKWARD_LAUNCH = (1024, 4)
#: Tiles a program of the backward's sums walks (``_backward_sums_kernel``): its reductions across the program, and
#: its start, once per that many tiles.
SUMS_ITERS = 16


@triton.jit
def _tile(b, t, g, P, C, GS: tl.constexpr, GS_P2: tl.constexpr, BLOCK: tl.constexpr):
    """Offsets, mask and float32 values of one group's tile."""
    p = t * BLOCK + tl.arange(0, BLOCK)
    c = g * GS + tl.arange(0, GS_P2)
    mask = (p < P)[:, None] & (tl.arange(0, GS_P2) < GS)[None, :]
    offs = (b.to(tl.int64) * P + p[:, None]) * C + c[None, :]
    return offs, mask, c


@triton.jit
def _part(b, t, g, P, CP, G: tl.constexpr, GS: tl.constexpr, GS_P2: tl.constexpr, BLOCK: tl.constexpr,
          PARTS: tl.constexpr):
    """(part k holding the group, offsets of one group's tile in that part [B, P, CP]): the same elements
    as ``_tile``'s, for tensors held in parts of CP = C / PARTS channels (an argument, not computed here,
    so that Triton knows its divisibility and vectorises the accesses)."""
    k = g // (G // PARTS)
    p = t * BLOCK + tl.arange(0, BLOCK)
    c = (g - k * (G // PARTS)) * GS + tl.arange(0, GS_P2)
    return k, (b.to(tl.int64) * P + p[:, None]) * CP + c[None, :]


@triton.jit
def _stats_kernel(x_ptr, mean_ptr, m2_ptr, P, C, T, G: tl.constexpr, GS: tl.constexpr, GS_P2: tl.constexpr,
                  BLOCK: tl.constexpr):
    g, t, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    offs, mask, _ = _tile(b, t, g, P, C, GS, GS_P2, BLOCK)
    x = tl.load(x_ptr + offs, mask=mask, other=0.0).to(tl.float32)
    n = tl.sum(mask.to(tl.float32))
    mean = tl.sum(x) / n
    d = tl.where(mask, x - mean, 0.0)
    out = (b * T + t) * G + g
    tl.store(mean_ptr + out, mean)
    tl.store(m2_ptr + out, tl.sum(d * d))


@triton.jit
def _gelu_and_slope(a):
    """(GELU(a), GELU'(a)): a Phi(a) and Phi(a) + a phi(a) with the standard normal's cdf Phi and pdf phi."""
    cdf = 0.5 * (1.0 + tl.math.erf(a * 0.7071067811865476))
    return a * cdf, cdf + a * 0.3989422804014327 * tl.exp(-0.5 * a * a)


@triton.jit
def _apply_kernel(x_ptr, y_ptr, mean_ptr, rstd_ptr, w_ptr, bias_ptr, P, C, CP, PART_SIZE, G: tl.constexpr,
                  GS: tl.constexpr, GS_P2: tl.constexpr, BLOCK: tl.constexpr, GELU: tl.constexpr, PARTS: tl.constexpr):
    g, t, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    offs, mask, c = _tile(b, t, g, P, C, GS, GS_P2, BLOCK)
    y_offs = offs
    if PARTS > 1:  # y is one buffer [PARTS, B, P, CP] of parts of PART_SIZE elements
        k, part_offs = _part(b, t, g, P, CP, G, GS, GS_P2, BLOCK, PARTS)
        y_offs = k.to(tl.int64) * PART_SIZE + part_offs
    cm = tl.arange(0, GS_P2) < GS
    x = tl.load(x_ptr + offs, mask=mask, other=0.0).to(tl.float32)
    mean = tl.load(mean_ptr + b * G + g)
    rstd = tl.load(rstd_ptr + b * G + g)
    w = tl.load(w_ptr + c, mask=cm, other=0.0).to(tl.float32)
    bias = tl.load(bias_ptr + c, mask=cm, other=0.0).to(tl.float32)
    a = (x - mean) * rstd * w[None, :] + bias[None, :]
    if GELU:
        a, _ = _gelu_and_slope(a)
    tl.store(y_ptr + y_offs, a.to(y_ptr.dtype.element_ty), mask=mask)


@triton.jit
def _load_dy(dy0_ptr, dy1_ptr, dy2_ptr, offs, mask, b, t, g, P, CP, G: tl.constexpr, GS: tl.constexpr,
             GS_P2: tl.constexpr, BLOCK: tl.constexpr, PARTS: tl.constexpr):
    """dL/dy of one group's tile, float32: from the one tensor, or from the part holding the group."""
    if PARTS == 1:
        dy = tl.load(dy0_ptr + offs, mask=mask, other=0.0)
    else:
        k, part_offs = _part(b, t, g, P, CP, G, GS, GS_P2, BLOCK, PARTS)
        if k == 0:
            dy = tl.load(dy0_ptr + part_offs, mask=mask, other=0.0)
        elif k == 1:
            dy = tl.load(dy1_ptr + part_offs, mask=mask, other=0.0)
        else:
            dy = tl.load(dy2_ptr + part_offs, mask=mask, other=0.0)
    return dy.to(tl.float32)


@triton.jit
def _grad_a(x_ptr, dy, offs, mask, c, mean, rstd, w_ptr, bias_ptr, GS: tl.constexpr, GS_P2: tl.constexpr,
            GELU: tl.constexpr):
    """(x^, dL/da, gamma) of a tile from dL/dy ``dy``; zero where masked."""
    cm = tl.arange(0, GS_P2) < GS
    x = tl.load(x_ptr + offs, mask=mask, other=0.0).to(tl.float32)
    w = tl.load(w_ptr + c, mask=cm, other=0.0).to(tl.float32)
    xhat = tl.where(mask, (x - mean) * rstd, 0.0)
    if GELU:
        bias = tl.load(bias_ptr + c, mask=cm, other=0.0).to(tl.float32)
        _, slope = _gelu_and_slope(xhat * w[None, :] + bias[None, :])
        dy = dy * slope
    return xhat, dy, w


@triton.jit
def _backward_sums_kernel(x_ptr, dy0_ptr, dy1_ptr, dy2_ptr, mean_ptr, rstd_ptr, w_ptr, bias_ptr, s1_ptr, s2_ptr,
                          dw_ptr, db_ptr, P, C, CP, T, G: tl.constexpr, GS: tl.constexpr, GS_P2: tl.constexpr,
                          BLOCK: tl.constexpr, ITERS: tl.constexpr, GELU: tl.constexpr, PARTS: tl.constexpr):
    """One group's sums over ``ITERS`` consecutive tiles (chunk t): the products are added up element-wise in
    float32 registers, tile after tile, and reduced across the program once at the end."""
    g, t, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    mean = tl.load(mean_ptr + b * G + g)
    rstd = tl.load(rstd_ptr + b * G + g)
    sum_gx = tl.zeros([BLOCK, GS_P2], tl.float32)
    sum_gx_xhat = tl.zeros([BLOCK, GS_P2], tl.float32)
    sum_da_xhat = tl.zeros([BLOCK, GS_P2], tl.float32)
    sum_da = tl.zeros([BLOCK, GS_P2], tl.float32)
    for i in range(ITERS):
        tile = t * ITERS + i
        offs, mask, c = _tile(b, tile, g, P, C, GS, GS_P2, BLOCK)
        dy = _load_dy(dy0_ptr, dy1_ptr, dy2_ptr, offs, mask, b, tile, g, P, CP, G, GS, GS_P2, BLOCK, PARTS)
        xhat, da, w = _grad_a(x_ptr, dy, offs, mask, c, mean, rstd, w_ptr, bias_ptr, GS, GS_P2, GELU)
        gx = da * w[None, :]
        sum_gx += gx
        sum_gx_xhat += gx * xhat
        sum_da_xhat += da * xhat
        sum_da += da
    out = (b * T + t) * G + g
    tl.store(s1_ptr + out, tl.sum(sum_gx))
    tl.store(s2_ptr + out, tl.sum(sum_gx_xhat))
    row = (b * T + t) * C
    c = g * GS + tl.arange(0, GS_P2)
    cm = tl.arange(0, GS_P2) < GS
    tl.store(dw_ptr + row + c, tl.sum(sum_da_xhat, axis=0), mask=cm)
    tl.store(db_ptr + row + c, tl.sum(sum_da, axis=0), mask=cm)


@triton.jit
def _backward_dx_kernel(x_ptr, dy0_ptr, dy1_ptr, dy2_ptr, dx_ptr, mean_ptr, rstd_ptr, w_ptr, bias_ptr, s1_ptr,
                        s2_ptr, P, C, CP, inv_n, G: tl.constexpr, GS: tl.constexpr, GS_P2: tl.constexpr,
                        BLOCK: tl.constexpr, GELU: tl.constexpr, PARTS: tl.constexpr):
    g, t, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    offs, mask, c = _tile(b, t, g, P, C, GS, GS_P2, BLOCK)
    mean = tl.load(mean_ptr + b * G + g)
    rstd = tl.load(rstd_ptr + b * G + g)
    dy = _load_dy(dy0_ptr, dy1_ptr, dy2_ptr, offs, mask, b, t, g, P, CP, G, GS, GS_P2, BLOCK, PARTS)
    xhat, da, w = _grad_a(x_ptr, dy, offs, mask, c, mean, rstd, w_ptr, bias_ptr, GS, GS_P2, GELU)
    s1 = tl.load(s1_ptr + b * G + g) * inv_n
    s2 = tl.load(s2_ptr + b * G + g) * inv_n
    dx = rstd * (da * w[None, :] - s1 - xhat * s2)
    tl.store(dx_ptr + offs, dx.to(dx_ptr.dtype.element_ty), mask=mask)


def _launch_shape(x: torch.Tensor, groups: int, tile: int) -> tuple[int, int, int, int, int, int, int]:
    B, C, H, W = x.shape
    gs = C // groups
    gs_p2 = triton.next_power_of_2(gs)
    block = max(16, tile // gs_p2)
    P = H * W
    return B, C, P, gs, gs_p2, block, triton.cdiv(P, block)


def _combine(tile_mean: torch.Tensor, tile_m2: torch.Tensor, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Chan et al.'s pairwise combination of per-tile (mean, M2) [B, T, G] with tile counts [T]: mean and
    biased variance [B, G] (float64 for the few numbers involved)."""
    m, m2, n = tile_mean.double(), tile_m2.double(), counts.double()[None, :, None]
    total = n.sum(1)
    mean = (n * m).sum(1) / total
    var = (m2.sum(1) + (n * (m - mean[:, None]) ** 2).sum(1)) / total
    return mean, var


def _check_parts(C: int, groups: int, parts: int) -> None:
    if not 1 <= parts <= 3 or groups % parts or C % parts:
        raise ValueError(f"GroupNorm kernels: {parts} parts of {C} channels in {groups} groups")


def forward(x: torch.Tensor, groups: int, weight: torch.Tensor, bias: torch.Tensor, eps: float, gelu: bool,
            parts: int = 1) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """([y] or y's ``parts`` channel blocks, each channels-last [B, C / parts, H, W]; mean [B, G] float32,
    rstd [B, G] float32) of a channels-last x."""
    tile, warps = FORWARD_LAUNCH
    B, C, P, gs, gs_p2, block, T = _launch_shape(x, groups, tile)
    _check_parts(C, groups, parts)
    tile_mean = torch.empty(B, T, groups, device=x.device, dtype=torch.float32)
    tile_m2 = torch.empty_like(tile_mean)
    grid = (groups, T, B)
    _stats_kernel[grid](x, tile_mean, tile_m2, P, C, T, G=groups, GS=gs, GS_P2=gs_p2, BLOCK=block, num_warps=warps)
    counts = (P - torch.arange(T, device=x.device) * block).clamp(max=block) * gs
    mean, var = _combine(tile_mean, tile_m2, counts)
    rstd = torch.rsqrt(var + eps).float()
    mean = mean.float()
    H, W = x.shape[2:]
    y = torch.empty(parts, B, H, W, C // parts, device=x.device, dtype=x.dtype)
    _apply_kernel[grid](x, y, mean, rstd, weight, bias, P, C, C // parts, y[0].numel(), G=groups, GS=gs,
                        GS_P2=gs_p2, BLOCK=block, GELU=gelu, PARTS=parts, num_warps=warps)
    return [part.permute(0, 3, 1, 2) for part in y], mean, rstd


def backward(dys: list[torch.Tensor], x: torch.Tensor, mean: torch.Tensor, rstd: torch.Tensor, groups: int,
             weight: torch.Tensor, bias: torch.Tensor, gelu: bool, need_x: bool
             ) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
    """(dx or None, dgamma, dbeta) in x's, the weight's and the bias's dtypes, from dL/dy as ``forward``
    gave y: one tensor or its parts."""
    tile, warps = BACKWARD_LAUNCH
    B, C, P, gs, gs_p2, block, T = _launch_shape(x, groups, tile)
    parts = len(dys)
    _check_parts(C, groups, parts)
    dys = [dy.contiguous(memory_format=torch.channels_last) for dy in dys]
    dys += [dys[-1]] * (3 - parts)  # the kernels take three pointers; the unused ones are never read
    iters = min(SUMS_ITERS, T)
    chunks = triton.cdiv(T, iters)
    s1 = torch.empty(B, chunks, groups, device=x.device, dtype=torch.float32)
    s2 = torch.empty_like(s1)
    dw = torch.empty(B, chunks, C, device=x.device, dtype=torch.float32)
    db = torch.empty_like(dw)
    _backward_sums_kernel[(groups, chunks, B)](x, *dys, mean, rstd, weight, bias, s1, s2, dw, db, P, C, C // parts,
                                               chunks, G=groups, GS=gs, GS_P2=gs_p2, BLOCK=block, ITERS=iters,
                                               GELU=gelu, PARTS=parts, num_warps=warps)
    dx = None
    if need_x:
        dx = torch.empty_like(x, memory_format=torch.channels_last)
        _backward_dx_kernel[(groups, T, B)](x, *dys, dx, mean, rstd, weight, bias, s1.sum(1), s2.sum(1), P, C,
                                            C // parts, 1.0 / (P * gs), G=groups, GS=gs, GS_P2=gs_p2, BLOCK=block,
                                            GELU=gelu, PARTS=parts, num_warps=warps)
    return dx, dw.sum((0, 1)).to(weight.dtype), db.sum((0, 1)).to(bias.dtype)
