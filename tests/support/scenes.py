"""Small scenes, cameras and the reference comparison shared by the rasteriser tests.

Conventions (SPEC section 1): OpenCV cameras (x right, y down, z forward), ``viewmats`` world-to-camera
4x4, intrinsics in pixels, quaternions wxyz, scales linear, opacities in [0, 1]. Scenes are dicts of torch
float32 tensors keyed by ``rasterization``'s argument names (means, quats, scales, opacities, colors).

Comparison against the float64 reference (``assert_matches_reference``): the SPEC image has three kinds of
discrete decisions per pixel: the touch rule o exp(-sigma) >= 1/255, the early stop T (1 - alpha) <= 1e-4
and the front-to-back order by camera depth. Where the float64 value lies within float32 rounding of a
threshold (or two depths within float32 rounding of each other: the guitar's quantised positions give
many exact depth ties), a correct float32 renderer may decide the other way and the pixel legitimately
differs by one Gaussian's contribution (up to 1/255 for a touch; up to T <= 1e-4 / (1 - max_alpha) for a
stop or a swap at the stop; a swap elsewhere leaves alpha alone and moves the colour by
T alpha_i alpha_j |c_i - c_j|). The reference reports, per pixel, how close every decision came;
pixels closer than ``KNIFE_EDGE`` / ``ORDER_EDGE`` are "knife-edge". They must be a counted fraction, are
left out of the per-pixel colour/depth maxima (never out of the PSNR), and their alpha is still bounded by
the tolerance plus one flipped decision.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from scenesplat_stereo.raster.reference import as_renderer_sees, reference_rasterization

# Tolerances against the float64 reference (the acceptance numbers).
PSNR_MIN_DB = 50.0  # RGB, peak 1, per image
ALPHA_TOL = 1e-3  # max |alpha difference|
# Depth: D = sum_i w_i z_i with the same weights w_i as the colours (sum w_i = alpha <= 1), so a weight error
# at the alpha tolerance moves D by at most ALPHA_TOL * z_max: depth is compared relative to the largest
# visible depth z_max of the camera. ED = D / alpha then errs by at most (|dD| + ED |d alpha|) / alpha
# <= 2 ALPHA_TOL z_max / alpha, compared wherever the reference alpha > 0 (a composited pixel has
# alpha >= 1/255, so the 1e-10 floor of ED only acts where alpha = 0 and ED = 0).
DEPTH_TOL = ALPHA_TOL
# Knife-edge margin, in log units (relative distance of o exp(-sigma) to 1/255, or of T (1 - alpha) to 1e-4).
# float32 carries ~6e-8 relative error per operation; sigma (a quadratic form of pixel offsets ~1e2 px)
# collects ~1e-5 absolute error; 1e-4 leaves an order of magnitude of room.
KNIFE_EDGE = 1e-4
# Depth-order margin (relative depth gap of consecutive Gaussians at a pixel): the float32 camera depth
# r . mean + t carries a few ulps (~1e-7 relative) of error for scenes whose coordinates are not much larger
# than their depths.
ORDER_EDGE = 1e-6
# Random scenes of a few hundred Gaussians at 64x48 have a few knife-edge pixels in ten thousand.
MAX_KNIFE_EDGE_FRACTION = 0.005
# Per-pixel colour tolerance: alpha's, scaled by the largest reference colour. PSNR >= 50 dB alone would
# let a bug at a few pixels through (one pixel off by 0.1 in a 64x48 image still scores ~60 dB).
RGB_TOL = ALPHA_TOL


def intrinsics(width: int, height: int, fov_x_deg: float = 60.0, cx: float | None = None,
               cy: float | None = None) -> torch.Tensor:
    """Pinhole K [3,3] float32 in pixels, square pixels, principal point at the image centre by default."""
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    return torch.tensor([[fx, 0.0, cx], [0.0, fx, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)


def look_at(eye: Sequence[float], target: Sequence[float], down: Sequence[float] = (0.0, 1.0, 0.0)) -> torch.Tensor:
    """World-to-camera 4x4 float32 of an OpenCV camera at ``eye`` looking at ``target``; image y along ``down``."""
    eye_, target_, down_ = (np.asarray(v, dtype=np.float64) for v in (eye, target, down))
    z = target_ - eye_
    z /= np.linalg.norm(z)
    y = down_ - np.dot(down_, z) * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], axis=1)
    c2w[:3, 3] = eye_
    return torch.from_numpy(np.linalg.inv(c2w)).to(torch.float32)


def orbit_cameras(center: Sequence[float], radius: float, n: int, width: int, height: int,
                  fov_x_deg: float = 50.0, elevation_deg: float = 20.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmats [n,4,4], Ks [n,3,3]): n cameras on a circle around ``center`` (world y down), looking at it."""
    c = np.asarray(center, dtype=np.float64)
    el = math.radians(elevation_deg)
    views = []
    for i in range(n):
        az = 2 * math.pi * i / n
        eye = c + radius * np.array([math.cos(el) * math.sin(az), -math.sin(el), math.cos(el) * math.cos(az)])
        views.append(look_at(eye, c))
    return torch.stack(views), intrinsics(width, height, fov_x_deg)[None].repeat(n, 1, 1)


def camera_rig(n: int, width: int, height: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmats [n,4,4], Ks [n,3,3]) near the origin looking at (0, 0, 4): camera 0 is the identity with a
    centred principal point; the others move up to 1 unit and have other focal lengths and off-centre
    principal points."""
    rng = np.random.default_rng(seed)
    views, Ks = [torch.eye(4)], [intrinsics(width, height, 60.0)]
    for _ in range(1, n):
        eye = rng.uniform(-1.0, 1.0, 3) * np.array([1.0, 0.5, 0.5])
        views.append(look_at(eye, (0.0, 0.0, 4.0)))
        Ks.append(intrinsics(width, height, rng.uniform(45, 75), width * rng.uniform(0.35, 0.65),
                             height * rng.uniform(0.35, 0.65)))
    return torch.stack(views), torch.stack(Ks)


def random_scene(n: int, seed: int, sh_degree: int | None = None, channels: int = 3,
                 depth: tuple[float, float] = (2.0, 6.0), scale: tuple[float, float] = (0.03, 0.4),
                 opacity: tuple[float, float] = (0.05, 1.0)) -> dict[str, torch.Tensor]:
    """n random Gaussians in front of the origin looking along +z (roughly inside a 70 degree cone).

    Depths uniform in ``depth``, scales log-uniform per axis in ``scale``, quaternions Gaussian random and
    NOT unit (the renderer normalises), opacities uniform in ``opacity``. Colours: SH coefficients
    [n, (d+1)^2, 3] when ``sh_degree`` is given, else plain colours [n, channels] in [0, 1].
    """
    g = torch.Generator().manual_seed(seed)
    z = depth[0] + (depth[1] - depth[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    xy = (2 * torch.rand(n, 2, generator=g, dtype=torch.float64) - 1) * 0.7 * z[:, None]
    means = torch.cat([xy, z[:, None]], 1)
    log_lo, log_hi = math.log(scale[0]), math.log(scale[1])
    scales = torch.exp(log_lo + (log_hi - log_lo) * torch.rand(n, 3, generator=g, dtype=torch.float64))
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64) * 1.7
    opacities = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    if sh_degree is None:
        colors = torch.rand(n, channels, generator=g, dtype=torch.float64)
    else:
        colors = 0.4 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
        colors[:, 0] *= 2.0
    scene = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors}
    return {k: v.to(torch.float32) for k, v in scene.items()}


def render_both(scene: dict[str, torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, width: int,
                height: int, **kwargs) -> tuple[tuple, tuple]:
    """Render with our Warp ``rasterization`` and with the float64 reference: ((colors, alphas, meta) x 2).

    The float parameters reach the reference rounded to float32 (``reference.as_renderer_sees``), the values
    the float32 renderer actually computes with.
    """
    from scenesplat_stereo.raster import rasterization

    ours = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                         viewmats, Ks, width, height, **kwargs)
    ref_kwargs = as_renderer_sees(kwargs)
    with torch.no_grad():
        ref = reference_rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                      scene["colors"], viewmats, Ks, width, height, **ref_kwargs)
    return ours, ref


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB with peak 1 over the whole of a and b (inf when equal)."""
    mse = float(((a.double() - b.double()) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def assert_finite(out: tuple, what: str = "rasterization") -> None:
    """No NaN or Inf in the colours, the alphas or any floating tensor of ``meta``."""
    colors, alphas, meta = out
    tensors = {"render_colors": colors, "render_alphas": alphas}
    tensors |= {f"meta[{k!r}]": v for k, v in meta.items() if torch.is_tensor(v) and v.is_floating_point()}
    for name, t in tensors.items():
        bad = ~torch.isfinite(t)
        if bool(bad.any()):
            idx = torch.nonzero(bad)[:5].tolist()
            raise AssertionError(f"{what}: {name} has {int(bad.sum())} non-finite values, first at {idx}")


def knife_edge_pixels(ref_meta: dict, order: bool = True) -> torch.Tensor:
    """[C,H,W] bool: pixels where a touch, stop or (with ``order``) depth-order decision lies within float32
    reach of flipping."""
    knife = (ref_meta["touch_margin"] < KNIFE_EDGE) | (ref_meta["stop_margin"] < KNIFE_EDGE)
    return knife | (ref_meta["order_margin"] < ORDER_EDGE) if order else knife


def assert_matches_reference(ours: tuple, ref: tuple, render_mode: str = "RGB",
                             max_knife_edge_fraction: float = MAX_KNIFE_EDGE_FRACTION,
                             max_alpha: float = 0.99, exact_depths: bool = False) -> dict[str, float]:
    """Hold our output to the reference's (see the module docstring); returns the measured errors.

    RGB: PSNR >= PSNR_MIN_DB per camera and, per pixel, |difference| <= RGB_TOL * max(1, max reference
    colour). Alpha: max |difference| <= ALPHA_TOL. Depth channels ("D": the alpha-weighted depth sum; "ED":
    expected depth) with DEPTH_TOL relative to the camera's largest visible depth. Knife-edge pixels (at
    most ``max_knife_edge_fraction`` of all) are left out of the per-pixel colour and depth maxima, and
    their alpha may differ by one flipped decision more. ``exact_depths``: the caller guarantees that the
    float32 camera depths are exact (identity rotation, zero translation), so depth ties and near-ties are
    ordered identically in both arithmetics and are not knife-edge.
    """
    assert_finite(ours)
    colors, alphas, _ = ours
    ref_colors, ref_alphas, meta = ref
    assert colors.shape == ref_colors.shape, f"render_colors {tuple(colors.shape)} != {tuple(ref_colors.shape)}"
    assert alphas.shape == ref_alphas.shape, f"render_alphas {tuple(alphas.shape)} != {tuple(ref_alphas.shape)}"
    colors, alphas = colors.detach().double().cpu(), alphas.detach().double().cpu()
    knife = knife_edge_pixels(meta, order=not exact_depths)
    n_knife, n_pix = int(knife.sum()), knife.numel()
    assert n_knife <= max_knife_edge_fraction * n_pix, (
        f"{n_knife} of {n_pix} pixels are knife-edge (a decision within float32 reach of flipping): the "
        f"scene does not allow a meaningful float32 comparison; at most {max_knife_edge_fraction * n_pix:.0f}")
    ok = ~knife
    stop_like = (meta["stop_margin"] < KNIFE_EDGE) | ((meta["order_margin"] < ORDER_EDGE) & (not exact_depths))
    jump = torch.where(stop_like, 1e-4 / (1 - max_alpha), 1.0 / 255.0) * 1.01
    report: dict[str, float] = {"knife_edge_pixels": float(n_knife)}
    alpha_err = (alphas - ref_alphas)[..., 0].abs()
    report["alpha_max_err"] = _max(alpha_err[ok])
    _assert_within(alpha_err, torch.where(knife, ALPHA_TOL + jump, ALPHA_TOL), "|alpha - reference|",
                   alphas[..., 0], ref_alphas[..., 0], knife)
    n_depth = 0 if render_mode == "RGB" else 1
    n_rgb = colors.shape[-1] - n_depth
    if n_rgb:
        per_cam = [psnr(colors[c, ..., :n_rgb], ref_colors[c, ..., :n_rgb]) for c in range(colors.shape[0])]
        report["psnr_min_db"] = min(per_cam)
        assert report["psnr_min_db"] >= PSNR_MIN_DB, f"PSNR per camera {per_cam} dB, need >= {PSNR_MIN_DB}"
        rgb_err = (colors[..., :n_rgb] - ref_colors[..., :n_rgb]).abs().amax(-1)
        report["rgb_max_err"] = _max(rgb_err[ok])
        rgb_tol = RGB_TOL * max(1.0, float(ref_colors[..., :n_rgb].abs().max()))
        _assert_within(rgb_err * ok, rgb_tol, "|colour - reference|", colors[..., 0], ref_colors[..., 0], knife)
    if n_depth:
        depths = torch.where(meta["visible"], meta["depths"], 0.0)
        z_max = torch.cat([depths, depths.new_ones(depths.shape[0], 1)], 1).amax(1)[:, None, None]  # >= 1: N may be 0
        d, d_ref, a_ref = colors[..., -1], ref_colors[..., -1], ref_alphas[..., 0]
        if render_mode.endswith("ED"):
            both_empty = (a_ref == 0) & (alphas[..., 0] == 0)
            assert bool((d[both_empty] == 0).all()), "ED is not 0 where nothing was composited"
            err = (d - d_ref).abs() * a_ref / (2 * z_max)  # <= DEPTH_TOL by the bound in the module docstring
            sel = ok & (a_ref > 0)
        else:
            err = (d - d_ref).abs() / z_max
            sel = ok
        report["depth_rel_err"] = _max(err[sel])
        _assert_within(err * sel, DEPTH_TOL, f"{render_mode} depth error / z_max", d, d_ref, knife)
    return report


def _assert_within(err: torch.Tensor, tol: torch.Tensor | float, what: str, ours: torch.Tensor,
                   ref: torch.Tensor, knife: torch.Tensor) -> None:
    """Fail naming the count, the worst value and the first offending [camera, row, col] with both values."""
    bad = err > tol
    if bool(bad.any()):
        first = tuple(torch.nonzero(bad)[0].tolist())
        raise AssertionError(
            f"{what} beyond tolerance at {int(bad.sum())} pixels (max {float(err.max()):.3g}); first at "
            f"[camera, row, col] = {list(first)}: ours {float(ours[first]):.7g}, reference {float(ref[first]):.7g}"
            f", error {float(err[first]):.3g} (knife-edge pixel: {bool(knife[first])})")


def _max(t: torch.Tensor) -> float:
    """Largest element of t, 0 when t is empty."""
    return float(t.max()) if t.numel() else 0.0
