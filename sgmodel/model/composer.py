"""Composer: the predictor's branch outputs -> the Gaussians' attributes (paper section 4.2-4.3, appendix A).

A pure function of tensors, no parameters. Everything is in the left (reference) camera's frame, OpenCV
axes, metres; pixels are canvas pixels with centres at +0.5; quaternions are wxyz.

Inputs of :func:`compose` (B scenes, an Hc x Wc canvas):

- ``front``, ``back``: [B,37,Hc,Wc] branch outputs of the front and back layer, channels as SPEC section 7
  "Branch channels": 0 opacity residual; 1-2 offset logits (u, v); 3-5 scale residuals (x, y, z);
  6-9 quaternion residual (w, x, y, z); 10-36 SH residuals, coefficient-major (channel 10 + 3k + c,
  k = 0..8 the SH coefficient, c = 0..2 the colour).
- ``dz``: [B,1,Hc,Wc] back-layer depth logits (metres after softplus).
- ``z``: [B,1,Hc,Wc] canvas depth z~ in metres, positive (already clipped to [Z_MIN, Z_MAX] and
  edge-replicated by the caller).
- ``rgb``: [B,3,Hc,Wc] canvas RGB~ in [0,1]; ``K``: [B,3,3] canvas intrinsics K~ in pixels;
  ``baseline``: [B] stereo baseline in metres (only the disparity-edge band uses it).

Output: dict(means [B,N,3] metres, quats [B,N,4] wxyz unit, scales [B,N,3] metres, opacities [B,N] in
[0,1], sh [B,N,9,3] degree-2 SH coefficients), Gaussians ordered front layer then back layer, each
row-major over the canvas (index v * Wc + u); N = 2 Hc Wc, or Hc Wc with ``back_layer=False``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from sgmodel.kernels import triton_kernels_run, triton_runs_on
from sgmodel.model.geometry import inverse_intrinsics

# --- Constants (paper appendix A "Attribute composition" unless noted) -------------------------------------
Z_MIN, Z_MAX = 0.1, 10.0  # eq. 1 and appendix A: depth clip in metres, applied BEFORE the composer
S_MIN, S_MAX = 1e-10, 3.0  # appendix A "Scale and rotation": scale clip, metres
KAPPA = 0.5  # appendix A "Scale and rotation": base footprint s0 = KAPPA z / sqrt(fx fy)
PHI_RANGE, PHI_MIN, PHI_SLOPE, PHI_SHIFT = 4.8, 0.2, 1.5, math.log(0.2)  # appendix A: phi(t), bounds (0.2, 5)
R_QUAT = 0.1  # appendix A "Scale and rotation": rotation residual scale r
ALPHA0 = 0.99  # appendix A "Opacity and colour": opacity base
C0 = 0.28209479177387814  # appendix A "Opacity and colour": SH DC constant 1 / (2 sqrt(pi))
SH_DECAY_BASE, SH_DECAY_RATE = 0.1, 0.25  # appendix A "Opacity and colour": degree-j residual scale 0.1 * 0.25^j
S_CAP_FRONT_EDGE = 0.3  # appendix A "Scale-residual clamps": front layer inside the edge band
S_CAP_BACK = 0.5  # appendix A "Scale-residual clamps": every back-layer Gaussian
EDGE_THRESHOLD = 0.05  # appendix A "Scale-residual clamps": relative disparity-gradient threshold
EDGE_DILATION = 8  # appendix A "Scale-residual clamps": band dilation in pixels (a 17 x 17 square)
BACK_POOL = 9  # section 4.3 eq. 4: back-layer anchor = max of z~ over a 9 x 9 neighbourhood
SOFT_BETA = 0.3  # appendix A "Edge-mask variants": soft mask floor beta
EDGE_MASKS = ("none", "hard", "soft")  # appendix A "Edge-mask variants"; "none" is the paper's model

# channel ranges of a front/back branch output (SPEC section 7 "Branch channels"); the predictor's heads
# are initialised by these names
CHANNELS = {
    "opacity": slice(0, 1),  # opacity residual delta_alpha (logit space)
    "offset": slice(1, 3),  # image-plane offset logits (u, v)
    "scale": slice(3, 6),  # scale residuals delta_s (x, y, z)
    "quat": slice(6, 10),  # quaternion residual delta_q (w, x, y, z)
    "sh": slice(10, 37),  # degree-2 SH residuals, coefficient-major: channel 10 + 3k + c
}
LAYER_CHANNELS = CHANNELS["sh"].stop  # 37
SH_COEFFS = 9  # degree 2
_SPLIT = tuple(s.stop - s.start for s in CHANNELS.values())  # the ranges are contiguous and in this order
_SH_DEGREE = (0, 1, 1, 1, 2, 2, 2, 2, 2)  # degree j of SH coefficient k
_QUAT_EPS = 1e-12  # norms below this give the identity quaternion (a zero vector has no direction)
#: The constants above as the fused kernels' compile-time arguments (``sgmodel.kernels.composer``).
KERNEL_CONSTANTS = dict(S_MIN=S_MIN, S_MAX=S_MAX, KAPPA=KAPPA, R_QUAT=R_QUAT, EPS2=_QUAT_EPS**2,
                        LOGIT=math.log(ALPHA0 / (1.0 - ALPHA0)), C0=C0, PHI_RANGE=PHI_RANGE, PHI_MIN=PHI_MIN,
                        PHI_SLOPE=PHI_SLOPE, PHI_SHIFT=PHI_SHIFT, DECAY1=SH_DECAY_BASE * SH_DECAY_RATE,
                        DECAY2=SH_DECAY_BASE * SH_DECAY_RATE**2)


def scale_cap(s_cap: float) -> float:
    """Upper bound c = 4 + ln(exp(s_cap) - 1) on a raw scale residual (appendix A "Scale-residual clamps")."""
    return 4.0 + math.log(math.expm1(s_cap))


def phi(t: torch.Tensor) -> torch.Tensor:
    """Bounded scale multiplier phi(t) = 4.8 sigmoid(1.5 t + ln 0.2) + 0.2, in (0.2, 5); phi(0) = phi'(0) = 1."""
    return PHI_RANGE * torch.sigmoid(PHI_SLOPE * t + PHI_SHIFT) + PHI_MIN


def back_depth(z: torch.Tensor, dz: torch.Tensor) -> torch.Tensor:
    """Back-layer depth [B,1,Hc,Wc], metres: the 9 x 9 stride-1 max of z~ plus softplus(dz) (eq. 4).

    The pool sees only pixels inside the canvas (padding with -inf), so a border pixel's anchor is the
    maximum over the part of its window that lies on the canvas."""
    r = BACK_POOL // 2
    padded = F.pad(z, (r, r, r, r), mode="constant", value=float("-inf"))
    return F.max_pool2d(padded, BACK_POOL, stride=1) + F.softplus(dz)


def gaussian_validity(valid: torch.Tensor, back_layer: bool = True) -> torch.Tensor:
    """Which Gaussians of ``compose`` stand on a stereo depth: [B,N] bool in ``compose``'s order (front layer,
    then back layer, each row-major over the canvas).

    valid [B,1,Hc,Wc] bool on the canvas (``geometry.disparity_validity``, edge-replicated like z~). A
    front-layer Gaussian is valid where its pixel is; a back-layer one where every canvas pixel of its
    BACK_POOL x BACK_POOL window is (its anchor is that window's largest z~, which an unmatched pixel sets
    to the far clamp). Not part of training (SPEC section 7 keeps N fixed): ``sgmodel predict`` drops the
    others."""
    front = valid.flatten(1)
    if not back_layer:
        return front
    r = BACK_POOL // 2
    invalid = F.pad((~valid).to(torch.float32), (r, r, r, r), mode="constant", value=0.0)
    return torch.cat([front, (F.max_pool2d(invalid, BACK_POOL, stride=1) == 0).flatten(1)], dim=1)


def edge_band(z: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor) -> torch.Tensor:
    """Dilated disparity-edge band [B,1,Hc,Wc] bool (appendix A "Scale-residual clamps"; not differentiable).

    Canvas disparity d~ = fx B / z~ (pixels). Relative gradient g = max(|d~(u+1,v) - d~(u,v)|,
    |d~(u,v+1) - d~(u,v)|) / max(d~(u,v), 1e-6), u the column and v the row; a forward difference whose
    neighbour lies outside the canvas is 0 (the last column has no horizontal term, the last row no vertical
    term). band = (g > EDGE_THRESHOLD) dilated by a (2 EDGE_DILATION + 1)^2 square."""
    with torch.no_grad():
        d = (K[:, 0, 0] * baseline).view(-1, 1, 1, 1) / z
        gu = F.pad((d[..., :, 1:] - d[..., :, :-1]).abs(), (0, 1, 0, 0))
        gv = F.pad((d[..., 1:, :] - d[..., :-1, :]).abs(), (0, 0, 0, 1))
        g = torch.maximum(gu, gv) / d.clamp_min(1e-6)
        edges = (g > EDGE_THRESHOLD).to(z.dtype)
        k = 2 * EDGE_DILATION + 1
        return F.max_pool2d(edges, k, stride=1, padding=EDGE_DILATION) > 0


def edge_gate(band: torch.Tensor, edge_mask: str, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Back-layer opacity multiplier in ``dtype`` from the edge band M (appendix A "Edge-mask variants"):
    "hard" gives M, "soft" gives SOFT_BETA + (1 - SOFT_BETA) M ("none" has no gate)."""
    m = band.to(dtype)
    if edge_mask == "hard":
        return m
    if edge_mask == "soft":
        return SOFT_BETA + (1.0 - SOFT_BETA) * m
    raise ValueError(f"edge_gate: edge_mask must be 'hard' or 'soft', got {edge_mask!r}")


def means(depth: torch.Tensor, offset_logits: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Centres [B,Hc*Wc,3], metres: z_l K~^-1 [u + 0.5 + du, v + 0.5 + dv, 1]^T with (du, dv) = sigmoid(o) - 1/2.

    depth [B,1,Hc,Wc] (z_l), offset_logits [B,2,Hc,Wc] (u, v); u the column, v the row. The same with and
    without the composer: centres stay depth-anchored in both."""
    B, _, H, W = depth.shape
    off = torch.sigmoid(offset_logits) - 0.5
    v, u = torch.meshgrid(torch.arange(H, device=depth.device, dtype=depth.dtype),
                          torch.arange(W, device=depth.device, dtype=depth.dtype), indexing="ij")
    du, dv = off.unbind(1)
    pix = torch.stack([u + 0.5 + du, v + 0.5 + dv, torch.ones_like(du)], dim=-1)
    rays = torch.einsum("bij,bhwj->bhwi", inverse_intrinsics(K), pix)  # [B,H,W,3]
    return (depth[:, 0, ..., None] * rays).reshape(B, H * W, 3)


def scales(depth: torch.Tensor, delta_s: torch.Tensor, K: torch.Tensor, cap: torch.Tensor | float | None,
           composer: bool = True) -> torch.Tensor:
    """Scales [B,Hc*Wc,3], metres.

    Composer: clip(s0 phi(min(delta_s, cap)), S_MIN, S_MAX), s0 = KAPPA z_l / sqrt(fx fy); ``cap`` is None
    (no cap), a number (every pixel) or a [B,1,Hc,Wc] tensor (+inf where uncapped).
    Without composer: clip(s0 exp(delta_s), S_MIN, S_MAX), ``cap`` ignored; the exponent ln s0 + delta_s is
    first limited to one unit beyond [ln S_MIN, ln S_MAX] (same value, finite gradients for huge residuals)."""
    B, _, H, W = depth.shape
    s0 = KAPPA * depth / torch.sqrt(K[:, 0, 0] * K[:, 1, 1]).view(-1, 1, 1, 1)
    if composer:
        if cap is not None:
            # minimum keeps its input for the backward: a copy of the 3 channels, not a view that would keep the
            # whole 37-channel branch alive until then (at the paper's batch, 375 MiB a layer)
            delta_s = torch.minimum(delta_s.contiguous(),
                                    torch.as_tensor(cap, dtype=delta_s.dtype, device=delta_s.device))
        s = (s0 * phi(delta_s)).clamp(S_MIN, S_MAX)
    else:
        log_s = (torch.log(s0) + delta_s).clamp(math.log(S_MIN) - 1.0, math.log(S_MAX) + 1.0)  # exp stays finite
        s = torch.exp(log_s).clamp(S_MIN, S_MAX)
    return s.permute(0, 2, 3, 1).reshape(B, H * W, 3)


def quats(delta_q: torch.Tensor, composer: bool = True) -> torch.Tensor:
    """Unit quaternions [B,Hc*Wc,4] wxyz: normalise((1,0,0,0) + R_QUAT delta_q) with the composer,
    normalise(delta_q) without; a vector of norm below 1e-12 gives the identity (1,0,0,0). (The paper writes
    q_id = (0,0,0,1) in xyzw order; it is the same identity rotation.)"""
    B, _, H, W = delta_q.shape
    q = delta_q.permute(0, 2, 3, 1).reshape(B, H * W, 4)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    # a new tensor either way: the backward keeps q, which must not be a view of the whole branch
    q = identity + R_QUAT * q if composer else q.contiguous()
    n2 = (q * q).sum(-1, keepdim=True)
    unit = q / torch.sqrt(n2.clamp_min(_QUAT_EPS**2))
    return torch.where(n2 > _QUAT_EPS**2, unit, identity)


def opacities(delta_alpha: torch.Tensor, gate: torch.Tensor | None = None, composer: bool = True
              ) -> torch.Tensor:
    """Opacities [B,Hc*Wc] in [0,1]: sigmoid(logit(ALPHA0) + delta_alpha) with the composer, sigmoid(delta_alpha)
    without; times ``gate`` [B,1,Hc,Wc] (the back-layer edge mask) when given."""
    B, _, H, W = delta_alpha.shape
    logit = delta_alpha + math.log(ALPHA0 / (1.0 - ALPHA0)) if composer else delta_alpha
    a = torch.sigmoid(logit)
    if gate is not None:
        a = a * gate.to(a.dtype)
    return a.reshape(B, H * W)


def sh(delta_c: torch.Tensor, rgb: torch.Tensor, composer: bool = True) -> torch.Tensor:
    """SH coefficients [B,Hc*Wc,9,3] from the 27 residual channels (coefficient-major, 3k + c).

    Composer: DC = (RGB~ - 0.5) / C0 + delta_c0 (the reference colour as base); degree j = 1, 2:
    SH_DECAY_BASE SH_DECAY_RATE^j delta_cj. Without composer: every coefficient is its residual (rgb unused)."""
    B, _, H, W = delta_c.shape
    c = delta_c.reshape(B, SH_COEFFS, 3, H, W)
    if composer:
        decay = torch.tensor([SH_DECAY_BASE * SH_DECAY_RATE**j for j in _SH_DEGREE[1:]],
                             dtype=c.dtype, device=c.device).view(1, SH_COEFFS - 1, 1, 1, 1)
        dc, higher = c.split([1, SH_COEFFS - 1], dim=1)  # a split's backward is one write (as in _layer)
        c = torch.cat([((rgb - 0.5) / C0).unsqueeze(1) + dc, decay * higher], dim=1)
    return c.permute(0, 3, 4, 1, 2).reshape(B, H * W, SH_COEFFS, 3)


def _layer(branch: torch.Tensor, depth: torch.Tensor, rgb: torch.Tensor, K: torch.Tensor,
           cap: torch.Tensor | float | None, gate: torch.Tensor | None, composer: bool) -> dict[str, torch.Tensor]:
    # one split, not five slices: its backward writes the branch's gradient once, where each slice's
    # would be a zero-filled full-size tensor, summed with the others
    opacity, offset, scale, quat, coeffs = branch.split(_SPLIT, dim=1)
    return dict(means=means(depth, offset, K),
                quats=quats(quat, composer),
                scales=scales(depth, scale, K, cap, composer),
                opacities=opacities(opacity, gate, composer),
                sh=sh(coeffs, rgb, composer))


class _FusedLayers(torch.autograd.Function):
    """The paper's model's attributes of the front and (if given) back layer through ``sgmodel.kernels.composer``:
    the layers' ``compose`` outputs, concatenated, from the branches in their own dtype. Gradients reach the
    branches and the back layer's depth; z~ and RGB~ get none (``compose`` sends here only inputs that need none)."""

    @staticmethod
    def forward(ctx, front: torch.Tensor, back: torch.Tensor | None, depth_back: torch.Tensor | None, z: torch.Tensor,
                rgb: torch.Tensor, K: torch.Tensor, band: torch.Tensor) -> tuple[torch.Tensor, ...]:
        from sgmodel.kernels import composer as kernels

        kinv = inverse_intrinsics(K).contiguous()
        rs = torch.sqrt(K[:, 0, 0] * K[:, 1, 1]).contiguous()
        band = band.to(torch.uint8).contiguous()
        ctx.save_for_backward(front, back, depth_back, z, kinv, rs, band)
        branches, depths, caps = _fused_layers(front, back, z, depth_back)
        return kernels.forward(branches, depths, rgb, kinv, rs, band, caps, KERNEL_CONSTANTS)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor):
        from sgmodel.kernels import composer as kernels

        front, back, depth_back, z, kinv, rs, band = ctx.saved_tensors
        branches, depths, caps = _fused_layers(front, back, z, depth_back)
        d_branches, d_depths = kernels.backward([g.contiguous() for g in grads], branches, depths,
                                                [False, ctx.needs_input_grad[2]][:len(branches)], kinv, rs, band,
                                                caps, KERNEL_CONSTANTS)
        d_back, d_depth_back = (d_branches[1], d_depths[1]) if back is not None else (None, None)
        return d_branches[0], d_back, d_depth_back, None, None, None, None


def _fused_layers(front: torch.Tensor, back: torch.Tensor | None, z: torch.Tensor, depth_back: torch.Tensor | None
                  ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[tuple[float, float, bool]]]:
    """(branches, depths, (cap in the edge band, cap elsewhere, whether the band applies) of each layer)."""
    front_caps = (scale_cap(S_CAP_FRONT_EDGE), math.inf, True)
    if back is None:
        return [front], [z], [front_caps]
    return [front, back], [z, depth_back], [front_caps, (0.0, scale_cap(S_CAP_BACK), False)]


def _fused_runs(front: torch.Tensor, z: torch.Tensor, rgb: torch.Tensor, composer: bool, edge_mask: str) -> bool:
    """Whether ``compose`` runs through ``_FusedLayers``: the paper's model (the composer on, no edge gate) where
    Triton runs (``triton_runs_on``: CUDA, or the CPU under Triton's interpreter), branches in float32 or half
    precision, and no gradient wanted for z~ or RGB~."""
    return (composer and edge_mask == "none" and triton_kernels_run(front) and triton_runs_on(z)
            and not (z.requires_grad or rgb.requires_grad))


def _check(name: str, t: object, shape: tuple[int | None, ...]) -> None:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"compose: {name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != a for s, a in zip(shape, t.shape)):
        want = "[" + ",".join("?" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"compose: {name} must have shape {want}, got {list(t.shape)}")
    if not t.is_floating_point():
        raise TypeError(f"compose: {name} must be floating point, got {t.dtype}")


def compose(front: torch.Tensor, back: torch.Tensor | None, dz: torch.Tensor | None, z: torch.Tensor,
            rgb: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor, *, back_layer: bool = True,
            edge_mask: str = "none", composer: bool = True) -> dict[str, torch.Tensor]:
    """Compose both layers' Gaussians (module docstring: inputs, units, output layout and order).

    Defaults are the paper's model. Options (the ablations of paper Table 4):

    - ``back_layer=False``: front layer only, N = Hc Wc; ``back`` and ``dz`` are ignored (may be None).
    - ``edge_mask``: "none" (paper default); "hard": back-layer opacity times the disparity-edge band M;
      "soft": back-layer opacity times SOFT_BETA + (1 - SOFT_BETA) M (appendix A "Edge-mask variants").
      M is :func:`edge_band`. Needs the back layer.
    - ``composer=False`` ("without composer"): the branch outputs become the attributes through plain
      activations, with no residual bases, no phi and no scale caps:
      centres as with the composer (front depth z~, back depth maxpool_9x9(z~) + softplus(dz), offsets
      sigmoid(o) - 1/2, so the centres stay depth-anchored);
      scale = clip(s0 exp(delta_s), S_MIN, S_MAX) with s0 = KAPPA z_l / sqrt(fx fy) kept for metric units
      (no phi, no scale caps in either layer); quat = normalise(delta_q) (identity for a zero vector, no
      (1,0,0,0) base, no R_QUAT); opacity = sigmoid(delta_alpha) (no ALPHA0 base); SH DC = delta_c0 (no
      reference-colour base); higher SH = delta_cj (no 0.1 * 0.25^j scaling). Edge masks still gate opacity.

    Works in float32 and float64 on any device, and on branches in float16 or bfloat16 (composed in float32);
    differentiable w.r.t. front, back, dz, z and rgb (the edge band is a non-differentiable selection). The
    paper's model on CUDA, with no gradient wanted for z or rgb (training and inference), runs in the fused
    kernels of ``sgmodel.kernels.composer`` (``_fused_runs``); everything else in the PyTorch operations here,
    which are what those kernels are tested against."""
    if edge_mask not in EDGE_MASKS:
        raise ValueError(f"compose: edge_mask must be one of {EDGE_MASKS}, got {edge_mask!r}")
    if edge_mask != "none" and not back_layer:
        raise ValueError(f"compose: edge_mask={edge_mask!r} gates the back layer; it needs back_layer=True")
    _check("front", front, (None, LAYER_CHANNELS, None, None))
    B, _, H, W = front.shape
    _check("z", z, (B, 1, H, W))
    _check("rgb", rgb, (B, 3, H, W))
    _check("K", K, (B, 3, 3))
    _check("baseline", baseline, (B,))
    if back_layer:
        _check("back", back, (B, LAYER_CHANNELS, H, W))
        _check("dz", dz, (B, 1, H, W))

    with torch.autocast("cuda" if front.is_cuda else "cpu", enabled=False):  # float32 under bf16 autocast too
        return _compose(front, back if back_layer else None, dz, z, rgb, K, baseline, edge_mask, composer)


def _compose(front: torch.Tensor, back: torch.Tensor | None, dz: torch.Tensor | None, z: torch.Tensor,
             rgb: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor, edge_mask: str, composer: bool
             ) -> dict[str, torch.Tensor]:
    """``compose`` of checked inputs, autocast off (``back`` None: the front layer alone)."""
    dtype = torch.float32 if front.dtype in (torch.float16, torch.bfloat16) else front.dtype
    K, baseline = K.to(dtype), baseline.to(dtype)
    band = edge_band(z, K, baseline) if (composer or edge_mask != "none") else None  # caps and/or gates
    depth_back = None if back is None else back_depth(z, dz.to(dtype))
    if _fused_runs(front, z, rgb, composer, edge_mask):
        out = _FusedLayers.apply(front, back, depth_back, z.to(dtype).contiguous(), rgb.to(dtype).contiguous(), K,
                                 band)
        return dict(zip(("means", "quats", "scales", "opacities", "sh"), out))
    front = front.to(dtype)
    if composer:
        front_cap = torch.where(band, scale_cap(S_CAP_FRONT_EDGE), float("inf")).to(front.dtype)
        back_cap = scale_cap(S_CAP_BACK)
    else:
        front_cap = back_cap = None
    layers = [_layer(front, z, rgb, K, front_cap, None, composer)]
    if back is not None:
        gate = None if band is None or edge_mask == "none" else edge_gate(band, edge_mask, front.dtype)
        layers.append(_layer(back.to(dtype), depth_back, rgb, K, back_cap, gate, composer))
    return {k: torch.cat([layer[k] for layer in layers], dim=1) for k in layers[0]}
