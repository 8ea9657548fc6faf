"""Independent float64 reference of the rasteriser, written only from SPEC section 2's eight steps.

``reference_rasterization`` has the signature and the outputs of ``scenesplat_stereo.raster.rasterization``
(gsplat 1.5's ``rasterization`` for the SPEC subset) but computes every image in torch float64, vectorised
as [pixels, Gaussians] matrices over 8x8 pixel blocks, each against the Gaussians that can reach it (an exact
pruning; no tile lists, no per-tile sorting). It is the truth the Warp rasteriser is held
against (forward tests) and, through torch autograd, the truth for its hand-written backward pass: every
operation is out of place and differentiable with respect to means, quats (unnormalised, normalised here),
scales, opacities, colors (SH coefficients or plain colours) and backgrounds. Culled Gaussians are removed
by index selection *before* any division, so they get exactly zero (never NaN) gradients.

It lives in the package (as gsplat ships ``_torch_impl.py``) so that ``bench render`` and
scripts/checks/gpu_parity.py find it in an installed copy too. It must never import ``scenesplat_stereo.raster``
(tests/scenesplat_stereo/raster/test_raster_forward.py checks this in a fresh interpreter).

Conventions (SPEC section 1): OpenCV cameras (x right, y down, z forward); ``viewmats`` are world-to-camera;
intrinsics in pixels; pixel (u, v) covers [u, u+1) x [v, v+1) and its centre is (u+0.5, v+0.5);
quaternions wxyz; scales linear; opacities in [0, 1]; SH coefficients [N, K, 3].

Besides gsplat-like projected quantities, ``meta`` holds per-pixel knife-edge margins (how close each
discrete decision of steps 6-7 came to its threshold: the touch rule and the early stop in log units, the
depth order as a relative gap), so tests can tell a genuine disagreement from one that float32 rounding
may legitimately flip; see ``_composite``.
"""

from __future__ import annotations

import math

import torch

from scenesplat_stereo.scene.harmonics import sh_basis

# SPEC section 2, step 3: tx/z, ty/z are clamped to the field of view widened by 0.15 W/fx (0.15 H/fy) per side.
FOV_CLAMP_MARGIN = 0.15
# SPEC section 2, step 6: a Gaussian touches a pixel when o exp(-sigma) >= 1/255.
TOUCH_ALPHA = 1.0 / 255.0
# SPEC section 2, step 7: a Gaussian with T (1 - alpha) <= 1e-4 is not composited and ends the pixel.
T_STOP = 1e-4
# SPEC section 2, step 8: "ED" = depth / max(alpha, 1e-10).
ED_ALPHA_FLOOR = 1e-10

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")
# Pixels are composited in BLOCK x BLOCK blocks against the Gaussians whose touch box, widened by
# PRUNE_SLACK (relative) and one pixel, reaches the block (an exact pruning; see _touch_extents).
BLOCK = 8
PRUNE_SLACK = 0.01
# Per-pixel diagnostics in meta (see _composite).
DIAGNOSTICS = ("n_composited", "touch_margin", "stop_margin", "order_margin")
# The [pixels, Gaussians] matrices hold at most this many entries at a time.
_MAX_PAIRS = 1 << 21


# The float parameters the float32 renderer computes with; the reference must judge the renderer's actual
# input: e.g. with max_alpha = 0.99, two stacked opaque Gaussians give T (1 - alpha) = (1 - 0.99)^2 =
# 1.0000000000000002e-4 > 1e-4 in float64 but (1 - float32(0.99))^2 = 9.99998e-5 <= 1e-4.
FLOAT32_PARAMS = ("near_plane", "far_plane", "eps2d", "max_alpha")


def as_renderer_sees(kwargs: dict) -> dict:
    """``kwargs`` of a ``rasterization`` call with ``FLOAT32_PARAMS`` rounded to float32 (``max_alpha``
    defaulting to float32(0.99)), to hand to ``reference_rasterization``."""
    out = {k: float(torch.tensor(v, dtype=torch.float32)) if k in FLOAT32_PARAMS else v for k, v in kwargs.items()}
    out.setdefault("max_alpha", float(torch.tensor(0.99, dtype=torch.float32)))
    return out


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N,3,3] from quaternions [N,4] wxyz (not necessarily unit; normalised here)."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return torch.stack(rows, -2)


def sh_colors(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """rgb [n,3] = max(SH(normalise(dirs)) + 0.5, 0) from coefficients [n,K,3], K >= (degree+1)^2 (first used)."""
    d = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
    basis = sh_basis(degree, d)  # [n, k]
    k = basis.shape[-1]
    return torch.clamp((basis[..., None] * coeffs[:, :k, :]).sum(-2) + 0.5, min=0.0)


def _project(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    antialiased: bool,
) -> dict[str, torch.Tensor]:
    """Steps 1-5 for one camera. Returns the surviving indices ``ids`` and their projected quantities."""
    R_view, t_view = viewmat[:3, :3], viewmat[:3, 3]
    p_all = means @ R_view.T + t_view  # step 1, camera frame [N,3]
    with torch.no_grad():
        in_depth = (p_all[:, 2] > near_plane) & (p_all[:, 2] < far_plane)
    ids = torch.nonzero(in_depth).flatten()
    p = p_all[ids]
    # Step 2: Sigma = R S S^T R^T, Sigma_cam = R_view Sigma R_view^T.
    M = quat_to_rotmat(quats[ids]) * scales[ids][:, None, :]
    sigma_cam = R_view @ (M @ M.transpose(-1, -2)) @ R_view.T
    # Step 3: Jacobian at the clamped (tx, ty, z).
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tx, ty, tz = p.unbind(-1)
    lim_x_neg = cx / fx + FOV_CLAMP_MARGIN * width / fx
    lim_x_pos = (width - cx) / fx + FOV_CLAMP_MARGIN * width / fx
    lim_y_neg = cy / fy + FOV_CLAMP_MARGIN * height / fy
    lim_y_pos = (height - cy) / fy + FOV_CLAMP_MARGIN * height / fy
    txc = tz * torch.clamp(tx / tz, min=-lim_x_neg, max=lim_x_pos)
    tyc = tz * torch.clamp(ty / tz, min=-lim_y_neg, max=lim_y_pos)
    zeros = torch.zeros_like(tz)
    J = torch.stack(
        [
            torch.stack([fx / tz, zeros, -fx * txc / (tz * tz)], -1),
            torch.stack([zeros, fy / tz, -fy * tyc / (tz * tz)], -1),
        ],
        -2,
    )  # [n,2,3]
    cov2d = J @ sigma_cam @ J.transpose(-1, -2)
    # Step 4: low-pass filter, det culling, antialiased compensation.
    a, b, c = cov2d[:, 0, 0] + eps2d, cov2d[:, 0, 1], cov2d[:, 1, 1] + eps2d
    det_blur = a * c - b * b
    with torch.no_grad():
        ok = det_blur > 0
    keep = torch.nonzero(ok).flatten()
    ids, p, cov2d, a, b, c, det_blur = ids[keep], p[keep], cov2d[keep], a[keep], b[keep], c[keep], det_blur[keep]
    o = opacities[ids]
    if antialiased:
        det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
        ratio = det / det_blur
        positive = ratio > 0
        # sqrt(max(ratio, 0)) written so that a zero ratio gives a zero (not NaN) gradient.
        o = o * torch.where(positive, torch.sqrt(torch.where(positive, ratio, torch.ones_like(ratio))), 0.0)
    # Step 5: screen-space mean and conic = inverse(Sigma2d').
    means2d = torch.stack([fx * p[:, 0] / p[:, 2] + cx, fy * p[:, 1] / p[:, 2] + cy], -1)
    conics = torch.stack([c / det_blur, -b / det_blur, a / det_blur], -1)  # (A, B, C) of [[A, B], [B, C]]
    return {"ids": ids, "depths": p[:, 2], "means2d": means2d, "conics": conics, "opacities": o}


def _touch_extents(conics: torch.Tensor, opacities: torch.Tensor) -> torch.Tensor:
    """[n,2] screen half-extents (x, y) in pixels beyond which a Gaussian cannot touch a pixel centre.

    Touching needs sigma <= ln(255 o) (step 6); on that ellipse |delta_x| <= sqrt(2 ln(255 o) Sigma2d'_xx)
    (likewise y). The box is widened by PRUNE_SLACK (relative) plus one pixel, so pruning by it is exact and
    the pairs it drops are far from the touch threshold. -1 where o < 1/255 (touches nothing).
    """
    A, B, Cc = conics.detach().unbind(-1)
    det = A * Cc - B * B
    cov_diag = torch.stack([Cc / det, A / det], -1)  # diagonal of Sigma2d' = inverse(conic)
    s = torch.log(255.0 * opacities.detach())
    ext = torch.sqrt(2.0 * torch.clamp(s, min=0.0)[:, None] * cov_diag) * (1.0 + PRUNE_SLACK) + 1.0
    return torch.where((s >= 0)[:, None], ext, -1.0)


def _composite(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    features: torch.Tensor,
    width: int,
    height: int,
    max_alpha: float,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """Steps 6-7 for one camera, Gaussians already sorted front to back.

    Returns the composited features [H*W, D] (no background), the final transmittance T [H*W] and
    per-pixel diagnostics: ``n_composited`` (int64), ``touch_margin`` = min over the Gaussians the pixel
    visits (up to and including the one that ends it) of |ln(o exp(-sigma)) - ln(1/255)|, and
    ``stop_margin`` = min over the touching visited ones of |ln(T (1 - alpha)) - ln(1e-4)|, and
    ``order_margin`` = min over consecutive touching visited ones of their relative depth gap
    (z_next - z) / z_next. A margin near 0 means float32 rounding may flip that decision or that order
    (+inf when there is no such Gaussian or pair).

    Pixels are processed in BLOCK x BLOCK blocks, each against the Gaussians whose widened touch box
    (``_touch_extents``) reaches it, in sorted order: a pruned Gaussian has alpha 0 at every pixel of the
    block, so the image is that of the full [pixels, Gaussians] matrices.
    """
    dtype, device = means2d.dtype, means2d.device
    ext = _touch_extents(conics, opacities)
    lo, hi = means2d.detach() - ext, means2d.detach() + ext
    blocks_out, blocks_T, blocks_pix = [], [], []
    diag: dict[str, list[torch.Tensor]] = {k: [] for k in DIAGNOSTICS}
    for v0 in range(0, height, BLOCK):
        for u0 in range(0, width, BLOCK):
            v1, u1 = min(v0 + BLOCK, height), min(u0 + BLOCK, width)
            vs, us = torch.meshgrid(torch.arange(v0, v1, device=device), torch.arange(u0, u1, device=device),
                                    indexing="ij")
            pix_ids = (vs * width + us).flatten()
            centres = torch.stack([us.flatten().to(dtype) + 0.5, vs.flatten().to(dtype) + 0.5], -1)
            reach = ((ext[:, 0] >= 0) & (hi[:, 0] >= u0 + 0.5) & (lo[:, 0] <= u1 - 0.5)
                     & (hi[:, 1] >= v0 + 0.5) & (lo[:, 1] <= v1 - 0.5))
            sel = torch.nonzero(reach).flatten()
            n = sel.numel()
            chunk = max(1, _MAX_PAIRS // max(n, 1))
            for start in range(0, centres.shape[0], chunk):
                out, T, d = _composite_pixels(centres[start : start + chunk], means2d[sel], conics[sel],
                                              opacities[sel], depths[sel], features[sel], max_alpha)
                blocks_out.append(out)
                blocks_T.append(T)
                blocks_pix.append(pix_ids[start : start + chunk])
                for k, v in d.items():
                    diag[k].append(v)
    pix = torch.cat(blocks_pix)
    n_pix = width * height
    out = torch.zeros(n_pix, features.shape[1], dtype=dtype, device=device).index_copy(0, pix, torch.cat(blocks_out))
    T = torch.ones(n_pix, dtype=dtype, device=device).index_copy(0, pix, torch.cat(blocks_T))
    diag_img = {k: torch.zeros(n_pix, dtype=v[0].dtype, device=device).index_copy(0, pix, torch.cat(v))
                for k, v in diag.items()}
    return out, T, diag_img


def _composite_pixels(
    centres: torch.Tensor,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    features: torch.Tensor,
    max_alpha: float,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """Steps 6-7 as [pixels, Gaussians] matrices: pixel centres [P,2] (x, y), n sorted Gaussians."""
    n = means2d.shape[0]
    # Step 6: delta = mean2d - c; sigma = 0.5 delta^T conic delta; touch rule.
    dx = means2d[None, :, 0] - centres[:, None, 0]
    dy = means2d[None, :, 1] - centres[:, None, 1]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    g = opacities * torch.exp(-sigma)
    touch = (sigma >= 0) & (g >= TOUCH_ALPHA)
    # Step 7: alpha, then the early stop, decided on detached values (a discrete decision).
    alpha = torch.where(touch, torch.clamp(g, max=max_alpha), 0.0)
    with torch.no_grad():
        t_next = torch.cumprod(1.0 - alpha, dim=1)  # T (1 - alpha) for each Gaussian in order
        stop = touch & (t_next <= T_STOP)
        n_stops = torch.cumsum(stop.to(torch.int64), dim=1)
        composited = touch & (n_stops == 0)
        visited = (n_stops - stop.to(torch.int64)) == 0
        tm = torch.where(visited & (sigma >= 0), (torch.log(g) - math.log(TOUCH_ALPHA)).abs(), math.inf)
        sm = torch.where(visited & touch, (torch.log(t_next) - math.log(T_STOP)).abs(), math.inf)
        # Depths ascend along a row, so the previous touching visited depth is a running max.
        z = torch.where(visited & touch, depths.detach(), -math.inf)
        z_prev = torch.cat([torch.full_like(z[:, :1], -math.inf), torch.cummax(z, dim=1).values[:, :-1]], 1)
        om = torch.where(visited & touch, (z - z_prev) / z, math.inf)
        inf = torch.full_like(centres[:, 0], math.inf)
        diag = {"n_composited": composited.sum(1), "touch_margin": tm.amin(1) if n else inf,
                "stop_margin": sm.amin(1) if n else inf, "order_margin": om.amin(1) if n else inf}
    a = torch.where(composited, alpha, 0.0)
    T_incl = torch.cumprod(1.0 - a, dim=1)
    T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
    T = T_incl[:, -1] if n else torch.ones_like(centres[:, 0])
    return (a * T_excl) @ features, T, diag


def _check_inputs(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    sh_degree: int | None,
    backgrounds: torch.Tensor | None,
    render_mode: str,
    rasterize_mode: str,
) -> None:
    N, C = means.shape[0], viewmats.shape[0]
    expect = {"means": (means, (N, 3)), "quats": (quats, (N, 4)), "scales": (scales, (N, 3))}
    expect |= {"opacities": (opacities, (N,)), "viewmats": (viewmats, (C, 4, 4)), "Ks": (Ks, (C, 3, 3))}
    for name, (t, shape) in expect.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"reference_rasterization: {name} has shape {tuple(t.shape)}, expected {shape}")
    if sh_degree is None:
        if colors.dim() != 2 or colors.shape[0] != N:
            raise ValueError(f"reference_rasterization: colors has shape {tuple(colors.shape)}, expected [N={N}, D]")
    elif not 0 <= sh_degree <= 3 or colors.dim() != 3 or colors.shape[0] != N or colors.shape[2] != 3:
        raise ValueError(f"reference_rasterization: colors {tuple(colors.shape)} / sh_degree {sh_degree}")
    elif colors.shape[1] < (sh_degree + 1) ** 2:
        raise ValueError(f"reference_rasterization: colors has K={colors.shape[1]} < (sh_degree+1)^2")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"reference_rasterization: render_mode {render_mode!r} not in {RENDER_MODES}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"reference_rasterization: rasterize_mode {rasterize_mode!r} not in {RASTERIZE_MODES}")
    n_channels = colors.shape[-1]
    if backgrounds is not None and tuple(backgrounds.shape) != (C, n_channels):
        raise ValueError(f"reference_rasterization: backgrounds has shape {tuple(backgrounds.shape)}, "
                         f"expected {(C, n_channels)}")


def reference_rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    rasterize_mode: str = "classic",
    max_alpha: float = 0.99,
    tile_size: int = 16,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """SPEC section 2 in float64: (render_colors [C,H,W,D], render_alphas [C,H,W,1], meta).

    Inputs as gsplat: means [N,3] world (metres), quats [N,4] wxyz, scales [N,3] linear, opacities [N] in
    [0,1], colors [N,K,3] SH coefficients when ``sh_degree`` is given (first (d+1)^2 used) else [N,D] plain
    colours, viewmats [C,4,4] world-to-camera OpenCV, Ks [C,3,3] pixels, backgrounds [C,D] over the
    colour channels. Depth channels (the camera z of step 1) get no background, as in gsplat; "RGB+D" and
    "RGB+ED" put depth as the last channel. ``tile_size`` is accepted and unused: the SPEC image does not
    depend on it. Outputs are float64 on the inputs' device.

    ``meta`` (per camera c, Gaussian g; zeros where culled): ``visible`` [C,N] bool, ``means2d`` [C,N,2],
    ``conics`` [C,N,3] (A, B, C of [[A,B],[B,C]] = inverse(Sigma2d')), ``depths`` [C,N], ``opacities`` [C,N]
    (the effective o of step 4); per pixel [C,H,W]: ``n_composited``, ``touch_margin``, ``stop_margin``,
    ``order_margin`` (see ``_composite``).
    """
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, backgrounds, render_mode,
                  rasterize_mode)
    f64 = torch.float64
    means, quats, scales, opacities, colors = (t.to(f64) for t in (means, quats, scales, opacities, colors))
    viewmats, Ks = viewmats.to(f64), Ks.to(f64)
    N, C = means.shape[0], viewmats.shape[0]
    want_rgb = render_mode in ("RGB", "RGB+D", "RGB+ED")
    want_depth = render_mode != "RGB"
    images, alphas = [], []
    meta_lists: dict[str, list[torch.Tensor]] = {
        k: [] for k in ("visible", "means2d", "conics", "depths", "opacities", *DIAGNOSTICS)
    }
    for cam in range(C):
        proj = _project(means, quats, scales, opacities, viewmats[cam], Ks[cam], width, height, near_plane,
                        far_plane, eps2d, rasterize_mode == "antialiased")
        ids = proj["ids"]
        order = torch.argsort(proj["depths"].detach(), stable=True)  # front to back, ties: lower index first
        feats = []
        if want_rgb:
            if sh_degree is None:
                feats.append(colors[ids])
            else:
                campos = -viewmats[cam, :3, :3].T @ viewmats[cam, :3, 3]
                feats.append(sh_colors(sh_degree, means[ids] - campos, colors[ids]))
        if want_depth:
            feats.append(proj["depths"][:, None])
        features = torch.cat(feats, -1)[order]
        out, T, diag = _composite(proj["means2d"][order], proj["conics"][order], proj["opacities"][order],
                                  proj["depths"][order], features, width, height, max_alpha)
        alpha = 1.0 - T
        # Step 8: background over the colour channels, "ED" = depth / max(alpha, 1e-10).
        channels = []
        if want_rgb:
            rgb = out[:, : out.shape[1] - int(want_depth)]
            if backgrounds is not None:
                rgb = rgb + T[:, None] * backgrounds[cam].to(f64)
            channels.append(rgb)
        if want_depth:
            depth = out[:, -1:]
            if render_mode.endswith("ED"):
                depth = depth / torch.clamp(alpha[:, None], min=ED_ALPHA_FLOOR)
            channels.append(depth)
        images.append(torch.cat(channels, -1).reshape(height, width, -1))
        alphas.append(alpha.reshape(height, width, 1))
        scatter = {"means2d": proj["means2d"], "conics": proj["conics"], "depths": proj["depths"],
                   "opacities": proj["opacities"]}
        for key, val in scatter.items():
            zeros = torch.zeros((N,) + tuple(val.shape[1:]), dtype=f64, device=means.device)
            meta_lists[key].append(zeros.index_copy(0, ids, val))
        meta_lists["visible"].append(torch.zeros(N, dtype=torch.bool, device=means.device).index_fill(0, ids, True))
        for key, val in diag.items():
            meta_lists[key].append(val.reshape(height, width))
    meta = {k: torch.stack(v) for k, v in meta_lists.items()}
    return torch.stack(images), torch.stack(alphas), meta
