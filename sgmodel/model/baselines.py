"""The paper's "stereo geometry without learned prediction" baselines (paper section 5), from any
encoder's depth; selected with ``--method naive-gs|forward-splat``.

* naive-GS: one isotropic Gaussian per left pixel at the stereo depth, with the composer's base footprint,
  identity rotation, the pixel's colour and opacity 0.99; rendered by ``sgmodel.model.render.render_views``.
* forward-splat: the left image warped into each target by its depth with a z-buffer (the nearest surface
  wins, holes stay empty).

Pixels without a valid stereo depth (``geometry.disparity_validity``) make no Gaussian and splat nothing:
``sgmodel.predict.inference`` passes their mask (naive-GS keeps N = H W and the caller drops or hides them).

Everything in the left camera frame (OpenCV axes, metres, pixel centres at +0.5), z = z-depth in metres
(``sgmodel.model.geometry.depth_from_disparity``).
"""

from __future__ import annotations

import torch

from sgmodel.model.geometry import unproject
from sgmodel.model.render import SH_COEFFS

METHODS = ("naive-gs", "forward-splat")
#: Real SH constant of degree 0 (SPEC section 1): colour = C0 * DC + 0.5.
SH_C0 = 0.28209479177387814
#: Opacity of a naive-GS Gaussian (paper section 5 baselines; the composer's base opacity, SPEC section 7).
NAIVE_OPACITY = 0.99
#: Base footprint s0 = FOOTPRINT z / sqrt(fx fy): half a pixel at depth z (SPEC section 7 "Composer").
FOOTPRINT = 0.5


def naive_gs(left: torch.Tensor, z: torch.Tensor, K: torch.Tensor) -> dict:
    """One Gaussian per left pixel, row-major: the Gaussians dict (contracts) with N = H W.

    left [B,3,H,W] in [0,1]; z [B,1,H,W] metres; K [B,3,3] pixels. mean = z K^-1 [u+0.5, v+0.5, 1];
    scales = s0 = 0.5 z / sqrt(fx fy) on every axis; quats (1,0,0,0); opacities 0.99;
    SH DC = (rgb - 0.5) / C0, degree 1 and 2 zero.
    """
    b, _, h, w = left.shape
    means = unproject(z, K).flatten(2).transpose(1, 2)                               # [B,N,3]
    s0 = FOOTPRINT * z.flatten(1) / torch.sqrt(K[:, 0, 0] * K[:, 1, 1])[:, None]     # [B,N]
    sh = left.new_zeros(b, h * w, SH_COEFFS, 3)
    sh[:, :, 0] = (left.flatten(2).transpose(1, 2) - 0.5) / SH_C0
    quats = left.new_zeros(b, h * w, 4)
    quats[..., 0] = 1.0
    return dict(means=means, quats=quats, scales=s0[..., None].expand(b, h * w, 3).contiguous(),
                opacities=left.new_full((b, h * w), NAIVE_OPACITY), sh=sh)


def forward_splat(left: torch.Tensor, z: torch.Tensor, K: torch.Tensor, viewmats: torch.Tensor,
                  Ks: torch.Tensor, width: int, height: int, near: float = 0.01,
                  valid: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp each left pixel to the target pixel that contains its projection; z-buffered.

    left [B,3,H,W]; z [B,1,H,W] metres; K [B,3,3]; viewmats [B,T,4,4] left-to-target; Ks [B,T,3,3];
    valid [B,1,H,W] bool or None: only these left pixels are warped (None: all).
    A left pixel centre X = z K^-1 [u+0.5, v+0.5, 1] lands in target pixel floor(K_t p / p_z) with p the
    point in the target camera (p_z > near). Where several land, the smallest target depth p_z wins (ties:
    the lowest source index). Returns images [B,T,3,height,width] (0 in holes) and coverage
    [B,T,1,height,width] (bool, True where some pixel landed). Not differentiable (a baseline).
    """
    b, _, h, w = left.shape
    t = viewmats.shape[1]
    pts = unproject(z, K).flatten(2)                                                  # [B,3,HW]
    p = viewmats[:, :, :3, :3] @ pts[:, None] + viewmats[:, :, :3, 3:]               # [B,T,3,HW]
    pz = p[:, :, 2]
    proj = Ks @ (p / torch.where(pz > near, pz, torch.ones_like(pz))[:, :, None])     # [B,T,3,HW]
    u, v = torch.floor(proj[:, :, 0]), torch.floor(proj[:, :, 1])
    ok = (pz > near) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    if valid is not None:
        ok &= valid.flatten(2)                                                        # [B,1,HW] over T
    # Flat target-pixel index over the whole batch, then a two-pass z-buffer with scatter_reduce.
    bt = torch.arange(b * t, device=left.device).reshape(b, t, 1) * (height * width)
    dst = (bt + v.clamp(0, height - 1).long() * width + u.clamp(0, width - 1).long())[ok]
    depth = pz[ok]
    src = torch.arange(h * w, device=left.device).expand(b, t, h * w)[ok]
    zbuf = torch.full((b * t * height * width,), float("inf"), dtype=depth.dtype, device=left.device)
    zbuf = zbuf.scatter_reduce(0, dst, depth, "amin")
    front = depth == zbuf[dst]
    winner = torch.full_like(zbuf, h * w, dtype=torch.long).scatter_reduce(0, dst[front], src[front], "amin")
    covered = winner < h * w
    colours = left.flatten(2).transpose(1, 2)                                         # [B,HW,3]
    batch = (torch.arange(b * t, device=left.device) // t).repeat_interleave(height * width)
    out = torch.zeros(b * t * height * width, 3, dtype=left.dtype, device=left.device)
    out[covered] = colours[batch[covered], winner[covered]]
    images = out.reshape(b, t, height, width, 3).permute(0, 1, 4, 2, 3)
    return images, covered.reshape(b, t, 1, height, width)
