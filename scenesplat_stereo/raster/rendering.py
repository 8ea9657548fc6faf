"""``rasterization``: the one entry point every part of the project renders through (SPEC section 2).

Same argument names, shapes and meaning as gsplat 1.5's ``rasterization`` for the subset used here.
Pipeline: project (per camera and Gaussian) -> scan of the tile counts -> SH colours (only when colours are
needed, compiled for the scene's degree; queued while the scan's total reaches the host) -> tile binning
(keys, sort, tile ranges) -> compositing (compiled for the channel count), then
background and expected depth as plain torch ops; each stage is one launch for a whole batch of scenes.
Differentiable with respect to means, quats, scales, opacities, colors and backgrounds through the stages'
autograd Functions.
"""

from __future__ import annotations

import math

import torch

from scenesplat_stereo.raster import autograd
from scenesplat_stereo.raster.binning import finish_binning, start_binning
from scenesplat_stereo.raster.sh import num_sh_bases

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")


def _check(cond: bool, msg) -> None:
    """ValueError with ``msg()`` unless ``cond`` (messages are formatted only on failure: the checks run on
    every call, and formatting them all costs host time comparable to a kernel launch)."""
    if not cond:
        raise ValueError(f"rasterization: {msg()}")


def rasterization(
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
    deterministic: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render N 3D Gaussians into C pinhole cameras, for one scene or a batch of scenes.

    Args:
        means: [..., N, 3] centres, world units.
        quats: [..., N, 4] rotations, wxyz, need not be unit (normalised inside; zero-norm ones are culled).
        scales: [..., N, 3] standard deviations along the rotated axes, world units (linear, not log).
        opacities: [..., N] in [0, 1] (not logits).
        colors: [..., N, K, 3] SH coefficients when ``sh_degree`` is given (K >= (sh_degree+1)^2), else
            [..., N, D] plain colours (or any features).
        viewmats: [..., C, 4, 4] world-to-camera, OpenCV axes (x right, y down, z forward).
        Ks: [..., C, 3, 3] pinhole intrinsics in pixels; pixel (u, v) is centred at (u + 0.5, v + 0.5).
        width, height: image size in pixels.
        near_plane, far_plane: camera-space z limits; Gaussians outside (near, far) are culled.
        eps2d: low-pass variance added to the screen-space covariance, pixels^2.
        sh_degree: 0..3 for SH colours; None for plain colours.
        backgrounds: [..., C, D] colour composited behind the Gaussians (colour channels only; depth
            channels get 0, as in gsplat).
        render_mode: "RGB", "D" (accumulated depth), "ED" (expected depth = D / alpha), "RGB+D", "RGB+ED";
            depth is appended as the last channel.
        rasterize_mode: "classic" or "antialiased" (opacity scaled by sqrt(det(S2d) / det(S2d + eps2d I))).
        max_alpha: per-Gaussian alpha clamp (gsplat 1.5.3 uses 0.999).
        tile_size: tile edge in pixels; the image does not depend on it.
        deterministic: bit-reproducible gradients on CUDA (a fixed-order reduction instead of float
            atomics; costs time and M x (6 + D) x 4 bytes, see docs/benchmarks.md). Not in gsplat.

    Batch dimensions ``...`` (none, one or more) are gsplat 1.5's: the same leading shape on every
    argument, one independent scene per index, whose C cameras see only its own N Gaussians. Every stage
    runs once for the whole batch (scene b's camera c is flat camera b * C + c of one big pass), and each
    scene's image and gradients equal, bit for bit on the CPU, those of rendering it alone.

    Returns:
        render_colors [..., C, H, W, D], render_alphas [..., C, H, W, 1], meta (screen-space intermediates,
        [..., C, N, ...]: means2d, conics, depths, opacities, radii, tiles_per_gauss; over the flat batch:
        tile_ranges [B * C * tiles, 2] and flatten_ids (entries (b * C + c) * N + g); tile_width,
        tile_height, tile_size, width, height, n_cameras = C, batch_dims = the leading shape).
    """
    _check(render_mode in RENDER_MODES, lambda: f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    _check(rasterize_mode in RASTERIZE_MODES,
           lambda: f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    _check(means.ndim >= 2 and means.shape[-1] == 3, lambda: f"means must be [..., N, 3], got {tuple(means.shape)}")
    batch, N = tuple(means.shape[:-2]), means.shape[-2]
    _check(quats.shape == (*batch, N, 4),
           lambda: f"quats must be [..., N, 4] = {[*batch, N, 4]}, got {tuple(quats.shape)}")
    _check(scales.shape == (*batch, N, 3),
           lambda: f"scales must be [..., N, 3] = {[*batch, N, 3]}, got {tuple(scales.shape)}")
    _check(opacities.shape == (*batch, N),
           lambda: f"opacities must be [..., N] = {[*batch, N]}, got {tuple(opacities.shape)}")
    _check(viewmats.ndim == len(batch) + 3 and viewmats.shape[:len(batch)] == batch and viewmats.shape[-2:] == (4, 4),
           lambda: f"viewmats must be [..., C, 4, 4] with the leading dims {list(batch)} of means, "
                   f"got {tuple(viewmats.shape)}")
    C = viewmats.shape[-3]
    _check(Ks.shape == (*batch, C, 3, 3),
           lambda: f"Ks must be [..., C, 3, 3] = {[*batch, C, 3, 3]}, got {tuple(Ks.shape)}")
    _check(int(width) >= 1 and int(height) >= 1, lambda: f"width and height must be >= 1, got {width}x{height}")
    _check(int(tile_size) >= 1 and int(tile_size) <= 64, lambda: f"tile_size must be in 1..64, got {tile_size}")
    _check(0.0 < max_alpha <= 1.0, lambda: f"max_alpha must be in (0, 1], got {max_alpha}")
    if sh_degree is not None:
        _check(0 <= sh_degree <= 3, lambda: f"sh_degree must be 0..3 or None, got {sh_degree}")
        _check(
            colors.ndim == len(batch) + 3 and colors.shape[:-2] == (*batch, N) and colors.shape[-1] == 3
            and colors.shape[-2] >= num_sh_bases(sh_degree),
            lambda: f"colors must be [..., N, K>={num_sh_bases(sh_degree)}, 3] = {[*batch, N, 'K', 3]} SH coefficients "
            f"for sh_degree={sh_degree}, got {tuple(colors.shape)}",
        )
    else:
        _check(colors.ndim == len(batch) + 2 and colors.shape[:-1] == (*batch, N),
               lambda: f"colors must be [..., N, D] = {[*batch, N, 'D']} without sh_degree, got {tuple(colors.shape)}")
    tensors = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                   viewmats=viewmats, Ks=Ks)
    if backgrounds is not None:
        tensors["backgrounds"] = backgrounds
    for name, t in tensors.items():
        _check(t.dtype == torch.float32, lambda: f"{name} must be float32, got {t.dtype}")
        _check(t.device == means.device, lambda: f"{name} is on {t.device}, means on {means.device}")
    with_rgb = render_mode in ("RGB", "RGB+D", "RGB+ED")
    with_depth = render_mode != "RGB"
    if backgrounds is not None and with_rgb:
        D = 3 if sh_degree is not None else colors.shape[-1]
        _check(backgrounds.shape == (*batch, C, D),
               lambda: f"backgrounds must be [..., C, D] = {[*batch, C, D]}, got {tuple(backgrounds.shape)}")
    width, height, tile_size = int(width), int(height), int(tile_size)

    # One flat batch: B scenes of N Gaussians end to end, B * C cameras (scene b's camera c is b * C + c).
    B = math.prod(batch)
    means_flat, viewmats_flat = means.reshape(B * N, 3), viewmats.reshape(B * C, 4, 4)
    proj = autograd.project(means_flat, quats.reshape(B * N, 4), scales.reshape(B * N, 3), opacities.reshape(B * N),
                            viewmats_flat, Ks.reshape(B * C, 3, 3), width, height, near_plane, far_plane, eps2d,
                            rasterize_mode == "antialiased", tile_size, B)
    # The scan's total travels to the host while the GPU evaluates the colours.
    pending = start_binning(proj, width, height, tile_size)
    channels = []
    if with_rgb:
        if sh_degree is not None:
            coeffs = colors.reshape(B * N, *colors.shape[-2:])
            channels.append(autograd.sh_colors(sh_degree, means_flat, viewmats_flat, coeffs, proj.radii, B))
        else:
            D = colors.shape[-1]
            channels.append(colors.reshape(B, 1, N, D).expand(B, C, N, D).reshape(B * C, N, D))
    if with_depth:
        channels.append(proj.depths[..., None])
    features = channels[0] if len(channels) == 1 else torch.cat(channels, dim=-1)
    features = features.contiguous()

    bins = finish_binning(pending)
    render, alphas, _ = autograd.composite(proj.means2d, proj.conics, features, proj.opacities, bins, width,
                                           height, tile_size, max_alpha, proj.touch_extents, deterministic)
    if render_mode in ("ED", "RGB+ED"):
        depth = render[..., -1:] / alphas.clamp_min(1e-10)
        render = torch.cat([render[..., :-1], depth], dim=-1)
    if backgrounds is not None and with_rgb:
        bg = backgrounds.reshape(B * C, backgrounds.shape[-1])[:, None, None, :] * (1.0 - alphas)
        if with_depth:
            bg = torch.cat([bg, torch.zeros_like(alphas)], dim=-1)
        render = render + bg

    per_camera = (*batch, C)
    meta = dict(
        means2d=proj.means2d.reshape(*per_camera, N, 2), conics=proj.conics.reshape(*per_camera, N, 3),
        depths=proj.depths.reshape(*per_camera, N), opacities=proj.opacities.reshape(*per_camera, N),
        radii=proj.radii.reshape(*per_camera, N, 2), tiles_per_gauss=proj.tiles_touched.reshape(*per_camera, N),
        tile_ranges=bins.tile_ranges, flatten_ids=bins.flatten_ids, tile_width=bins.tiles_x,
        tile_height=bins.tiles_y, tile_size=tile_size, width=width, height=height, n_cameras=C, batch_dims=batch,
    )
    return (render.reshape(*per_camera, height, width, render.shape[-1]),
            alphas.reshape(*per_camera, height, width, 1), meta)
