"""The rasteriser's hand-written backward pass against the float64 reference (scenesplat_stereo/raster/reference.py).

Truth: torch autograd through ``reference_rasterization`` (float64, written from SPEC section 2 only) and,
independently of autograd, central finite differences of that reference. The loss is a random cotangent
over every output, L = sum(w_c * render_colors) + sum(w_a * render_alphas), so every pixel, channel and
the alpha output all carry gradient. Agreement is measured per parameter group (means, quats, scales,
opacities, colors, backgrounds) as ||ours - reference|| / ||reference|| <= GRAD_RTOL.

Then the hard cases (section "stability"): gradients are finite everywhere and exactly zero for culled
Gaussians, and match the reference wherever the comparison is meaningful (no knife-edge pixel, see
tests/support/scenes.py). Finally the deterministic mode: bit-identical gradients from run to run, equal to the
atomic ones up to summation order, and the same for every tile size.

CUDA cases run when a GPU is present (the lead's GPU runs); on CPU, Warp runs kernels serially.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenesplat_stereo.raster import autograd, rasterization
from scenesplat_stereo.raster.composite_backward import composite_backward
from scenesplat_stereo.raster.reference import reference_rasterization
from tests.support.scenes import camera_rig, intrinsics, knife_edge_pixels, random_scene

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
# Acceptance: relative error of each parameter group's gradient against the float64 reference.
GRAD_RTOL = 1e-3
# Float parameters the float32 renderer computes with; the reference gets them rounded the same way.
_FLOAT32_PARAMS = ("near_plane", "far_plane", "eps2d", "max_alpha")
PARAMS = ("means", "quats", "scales", "opacities", "colors")
W, H = 40, 30


def cotangents(C: int, height: int, width: int, channels: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random float64 weights (w_c [C,H,W,channels], w_a [C,H,W,1]) of the loss."""
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(C, height, width, channels, generator=g, dtype=torch.float64),
            torch.randn(C, height, width, 1, generator=g, dtype=torch.float64))


def gradients(render, scene: dict, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
              backgrounds: torch.Tensor | None = None, seed: int = 0, dtype=torch.float32, device="cpu",
              **kwargs) -> tuple[dict[str, torch.Tensor | None], tuple]:
    """Gradients of L (see module docstring) for every parameter group, as float64 CPU tensors (None when
    the output does not depend on the group), and the render outputs."""
    if render is reference_rasterization:
        kwargs = {k: float(np.float32(v)) if k in _FLOAT32_PARAMS else v for k, v in kwargs.items()}
        kwargs.setdefault("max_alpha", float(np.float32(0.99)))
    leaves = {k: v.detach().to(device=device, dtype=dtype).requires_grad_() for k, v in scene.items()}
    if backgrounds is not None:
        leaves["backgrounds"] = backgrounds.detach().to(device=device, dtype=dtype).requires_grad_()
    out = render(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                 viewmats.to(device), Ks.to(device), width, height, backgrounds=leaves.get("backgrounds"),
                 **kwargs)
    w_c, w_a = cotangents(viewmats.shape[0], height, width, out[0].shape[-1], seed)
    loss = (out[0].double().cpu() * w_c).sum() + (out[1].double().cpu() * w_a).sum()
    names = list(leaves)
    grads = torch.autograd.grad(loss, [leaves[k] for k in names], allow_unused=True)
    return {k: None if g is None else g.detach().double().cpu() for k, g in zip(names, grads)}, out


def relative_error(ours: torch.Tensor | None, ref: torch.Tensor | None) -> float:
    """||ours - ref|| / ||ref|| (a missing gradient counts as zeros; 0 when both are zero)."""
    if ours is None and ref is None:
        return 0.0
    ours = torch.zeros_like(ref) if ours is None else ours
    ref = torch.zeros_like(ours) if ref is None else ref
    diff, norm = float((ours - ref).norm()), float(ref.norm())
    if norm == 0.0:
        return 0.0 if diff == 0.0 else math.inf
    return diff / norm


def assert_grads_match(ours: dict, ref: dict, rtol: float = GRAD_RTOL, what: str = "") -> dict[str, float]:
    errors = {k: relative_error(ours.get(k), ref.get(k)) for k in ref}
    bad = {k: e for k, e in errors.items() if not e <= rtol}
    assert not bad, f"{what}: relative gradient error > {rtol}: {bad} (all: {errors})"
    return errors


def assert_no_knife_edge(scene, viewmats, Ks, width, height, **kwargs) -> None:
    """The comparison is meaningful only if no discrete decision sits within float32 rounding of its
    threshold (tests/support/scenes.py). Depth-order ties are not knife-edge when every camera's z row is (0, 0, 1, 0):
    the camera depth is then the mean's z exactly, in float32 as in float64, and both break ties by index."""
    kwargs = {k: float(np.float32(v)) if k in _FLOAT32_PARAMS else v for k, v in kwargs.items()}
    kwargs.setdefault("max_alpha", float(np.float32(0.99)))
    with torch.no_grad():
        _, _, meta = reference_rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                             scene["colors"], viewmats, Ks, width, height, **kwargs)
    exact_depths = bool((viewmats[:, 2] == torch.tensor([0.0, 0.0, 1.0, 0.0])).all())
    n = int(knife_edge_pixels(meta, order=not exact_depths).sum())
    assert n == 0, f"test scene has {n} knife-edge pixels: pick another seed"


# ----------------------------------------------------------------------------------------------------------
# Agreement with autograd through the float64 reference, every mode
# ----------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
@pytest.mark.parametrize("render_mode", ["RGB", "D", "ED", "RGB+D", "RGB+ED"])
@pytest.mark.parametrize("sh_degree", [None, 0, 1, 2, 3])
def test_gradients_match_reference(sh_degree, render_mode, rasterize_mode, device):
    scene = random_scene(40, seed=3, sh_degree=sh_degree)
    viewmats, Ks = camera_rig(2, W, H)
    kwargs = dict(sh_degree=sh_degree, render_mode=render_mode, rasterize_mode=rasterize_mode)
    with_rgb = render_mode not in ("D", "ED")
    bg = torch.rand(2, 3, generator=torch.Generator().manual_seed(1)) if with_rgb else None
    assert_no_knife_edge(scene, viewmats, Ks, W, H, **kwargs)
    ref, _ = gradients(reference_rasterization, scene, viewmats, Ks, W, H, bg, dtype=torch.float64, **kwargs)
    ours, _ = gradients(rasterization, scene, viewmats, Ks, W, H, bg, device=device, **kwargs)
    assert all(ref[k] is not None and float(ref[k].norm()) > 0 for k in ("means", "quats", "scales", "opacities"))
    assert_grads_match(ours, ref, what=f"{sh_degree=} {render_mode} {rasterize_mode} on {device}")


@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
@pytest.mark.parametrize("channels", [1, 5])
def test_plain_feature_gradients(channels, render_mode):
    """Plain colours with D != 3 (any feature vector), with backgrounds of D channels."""
    scene = random_scene(30, seed=6, channels=channels)
    viewmats, Ks = camera_rig(2, W, H, seed=2)
    bg = torch.rand(2, channels, generator=torch.Generator().manual_seed(2))
    kwargs = dict(render_mode=render_mode, rasterize_mode="antialiased")
    assert_no_knife_edge(scene, viewmats, Ks, W, H, **kwargs)
    ref, _ = gradients(reference_rasterization, scene, viewmats, Ks, W, H, bg, dtype=torch.float64, **kwargs)
    ours, _ = gradients(rasterization, scene, viewmats, Ks, W, H, bg, **kwargs)
    assert_grads_match(ours, ref, what=f"{channels=} {render_mode}")


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_gradients_match_finite_differences(rasterize_mode):
    """Central differences of the float64 reference (no autograd involved) on a handful of entries of every
    group. Step 1e-6: truncation ~1e-12, rounding ~1e-16 |L| / 1e-6 ~ 1e-9, and no discrete decision of the
    scene lies within 1e-4 (log units) of its threshold, so none flips. "RGB+D", not "ED": ED's 1/alpha^2
    at nearly transparent pixels amplifies the float32 rounding of the forward pass itself (single entries
    then differ by ~1e-3 from float64 although the backward pass is exact); ED is held to the reference
    group-wise above."""
    sh_degree = 2
    scene = random_scene(25, seed=7, sh_degree=sh_degree)
    viewmats, Ks = camera_rig(2, W, H, seed=3)
    bg = torch.rand(2, 3, generator=torch.Generator().manual_seed(3))
    kwargs = dict(sh_degree=sh_degree, render_mode="RGB+D", rasterize_mode=rasterize_mode)
    assert_no_knife_edge(scene, viewmats, Ks, W, H, **kwargs)
    ours, _ = gradients(rasterization, scene, viewmats, Ks, W, H, bg, **kwargs)
    f64 = {k: v.double() for k, v in scene.items()} | {"backgrounds": bg.double()}
    w_c, w_a = cotangents(2, H, W, 4)

    def loss(params: dict) -> float:
        kw = {k: float(np.float32(v)) if k in _FLOAT32_PARAMS else v for k, v in kwargs.items()}
        with torch.no_grad():
            out = reference_rasterization(params["means"], params["quats"], params["scales"], params["opacities"],
                                          params["colors"], viewmats, Ks, W, H, backgrounds=params["backgrounds"],
                                          max_alpha=float(np.float32(0.99)), **kw)
        return float((out[0] * w_c).sum() + (out[1] * w_a).sum())

    rng = np.random.default_rng(0)
    checked = 0
    for name, value in f64.items():
        # Entries of Gaussians that actually reach pixels (the gradient of others is exactly zero anyway).
        candidates = torch.nonzero(ours[name].abs() > 1e-3 * float(ours[name].abs().max())).tolist()
        for idx in [candidates[i] for i in rng.choice(len(candidates), size=3, replace=False)]:
            h = 1e-6 * max(1.0, abs(float(value[tuple(idx)])))
            plus = {k: v.clone() for k, v in f64.items()}
            minus = {k: v.clone() for k, v in f64.items()}
            plus[name][tuple(idx)] += h
            minus[name][tuple(idx)] -= h
            fd = (loss(plus) - loss(minus)) / (2 * h)
            analytic = float(ours[name][tuple(idx)])
            scale = max(abs(fd), float(ours[name].abs().max()) * 1e-2)
            assert abs(analytic - fd) <= GRAD_RTOL * scale + 1e-6, (
                f"{name}{idx}: hand-written {analytic:.6g}, central difference {fd:.6g}")
            checked += 1
    assert checked == 3 * len(f64)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_sh_stage_matches_reference(sh_degree, device):
    """The SH stage alone, for view directions over the whole sphere (in renders they point roughly along
    the camera axis, where the normalisation hides errors along it) and of any length, from cameras at
    different centres and in different orientations, with extra bands beyond the degree (zero gradient), some
    channels clamped at 0 and some culled pairs (zero gradient). Gradients reach the means through the
    directions (summed over the cameras) and the coefficients; the reference takes the camera centre as
    -R^T t of each world-to-camera matrix."""
    from scenesplat_stereo.raster.reference import sh_colors as reference_sh_colors

    g = torch.Generator().manual_seed(sh_degree)
    C, N, K = 3, 64, 16
    means = torch.randn(N, 3, generator=g, dtype=torch.float64) * torch.exp(torch.randn(N, 1, generator=g))
    viewmats = torch.eye(4, dtype=torch.float64).repeat(C, 1, 1)
    for c in range(C):  # a random rotation (QR of a Gaussian matrix) and translation per camera
        q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        viewmats[c, :3, :3] = q * torch.sign(torch.diagonal(r))
        viewmats[c, :3, 3] = 2.0 * torch.randn(3, generator=g, dtype=torch.float64)
    coeffs = 0.5 * torch.randn(N, K, 3, generator=g, dtype=torch.float64)
    coeffs[:, 0] *= 4.0  # DC below -0.5 / C0 for about a quarter of the channels: clamped at 0
    radii = torch.ones(C, N, 2, dtype=torch.int32)
    radii[:, ::7] = 0
    v_colors = torch.randn(C, N, 3, generator=g, dtype=torch.float64)
    visible = (radii[..., 0] > 0).double()[..., None]

    m64, c64 = means.clone().requires_grad_(), coeffs.clone().requires_grad_()
    centres = -(viewmats[:, :3, :3].transpose(1, 2) @ viewmats[:, :3, 3:])[..., 0]
    ref_rgb = torch.stack([reference_sh_colors(sh_degree, m64 - centres[c], c64) for c in range(C)]) * visible
    ref_v_means, ref_v_coeffs = torch.autograd.grad((ref_rgb * v_colors).sum(), [m64, c64], allow_unused=True)
    clamped = float((ref_rgb == 0).double().mean() - (1 - visible).mean())
    assert clamped > 0.02, "some channels should be clamped at 0"

    m32 = means.float().to(device).requires_grad_()
    c32 = coeffs.float().to(device).requires_grad_()
    rgb = autograd.sh_colors(sh_degree, m32, viewmats.float().to(device), c32, radii.to(device))
    v_means, v_coeffs = torch.autograd.grad((rgb.double().cpu() * v_colors).sum(), [m32, c32], allow_unused=True)
    assert relative_error(rgb.detach().double().cpu(), ref_rgb.detach()) < 1e-6
    assert relative_error(v_coeffs.double().cpu(), ref_v_coeffs) < 1e-5
    assert bool((v_coeffs[:, (sh_degree + 1) ** 2:] == 0).all())
    if sh_degree == 0:
        assert v_means is None or bool((v_means == 0).all())
    else:
        assert relative_error(v_means.double().cpu(), ref_v_means) < 1e-5
        all_culled = torch.zeros(C, N, 2, dtype=torch.int32)
        rgb = autograd.sh_colors(sh_degree, m32, viewmats.float().to(device), c32, all_culled.to(device))
        v_means, v_coeffs = torch.autograd.grad(rgb.sum(), [m32, c32])
        assert bool((v_means == 0).all()) and bool((v_coeffs == 0).all()), "culled everywhere: no gradient"


# ----------------------------------------------------------------------------------------------------------
# Stability: hard cases. Finite everywhere, exactly zero when culled, and equal to the reference where the
# comparison is meaningful.
# ----------------------------------------------------------------------------------------------------------

def _scene(means, scales, quats=None, opacities=None, colors=None) -> dict[str, torch.Tensor]:
    means = torch.as_tensor(means, dtype=torch.float32).reshape(-1, 3)
    n = means.shape[0]
    scales = torch.as_tensor(scales, dtype=torch.float32).expand(n, 3).clone()
    if quats is None:
        quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    quats = torch.as_tensor(quats, dtype=torch.float32)
    opacities = torch.full((n,), 0.8) if opacities is None else torch.as_tensor(opacities, dtype=torch.float32)
    if colors is None:
        colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(n))
    return {"means": means, "quats": quats.reshape(n, 4), "scales": scales, "opacities": opacities.reshape(n),
            "colors": colors}


def check_hard_case(scene, viewmats, Ks, width, height, culled=(), compare=True, what="",
                    **kwargs) -> tuple[dict, dict | None]:
    """Gradients of every group (RGB+ED with backgrounds, so depth, ED's division and backgrounds take part)
    are finite; rows in ``culled`` get exact zeros; with ``compare``, they match the reference.
    Returns (ours, reference or None)."""
    kwargs.setdefault("render_mode", "RGB+ED")
    C = viewmats.shape[0]
    bg = torch.rand(C, scene["colors"].shape[-1], generator=torch.Generator().manual_seed(C))
    ours, out = gradients(rasterization, scene, viewmats, Ks, width, height, bg, **kwargs)
    for t in (out[0], out[1]):
        assert bool(torch.isfinite(t).all()), f"{what}: non-finite render"
    for name, g in ours.items():
        assert g is not None and bool(torch.isfinite(g).all()), f"{what}: non-finite gradient of {name}"
        if name != "backgrounds" and len(culled):
            rows = g[list(culled)]
            assert bool((rows == 0).all()), f"{what}: culled Gaussians {list(culled)} have {name} gradient {rows}"
    if compare:
        assert_no_knife_edge(scene, viewmats, Ks, width, height, **kwargs)
        ref, _ = gradients(reference_rasterization, scene, viewmats, Ks, width, height, bg, dtype=torch.float64,
                           **kwargs)
        assert_grads_match(ours, ref, what=what)
        return ours, ref
    return ours, None


def _identity_camera(width: int = 32, height: int = 24) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.eye(4)[None], intrinsics(width, height, 60.0)[None]


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_near_plane_and_camera_centre(rasterize_mode):
    """Behind the camera, exactly on the near plane, at the camera centre: culled (zero gradient); one
    just in front of the near plane and straddling it with a huge footprint; ordinary ones."""
    viewmats, Ks = _identity_camera()
    scene = _scene([[0.2, 0.1, -1.0], [0.0, 0.0, 0.01], [0.0, 0.0, 0.0], [0.01, -0.01, 0.05], [0.3, 0.2, 3.0],
                    [-0.4, 0.1, 2.5]], [[0.5, 0.5, 0.5], [0.3, 0.3, 0.3], [0.2, 0.2, 0.2], [0.02, 0.03, 0.2],
                                        [0.3, 0.2, 0.1], [0.2, 0.3, 0.4]], opacities=[0.9, 0.9, 0.9, 0.3, 0.8, 0.7])
    check_hard_case(scene, viewmats, Ks, 32, 24, culled=(0, 1, 2), rasterize_mode=rasterize_mode,
                    near_plane=0.01, what=f"near plane {rasterize_mode}")


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_extreme_scales_and_anisotropy(rasterize_mode):
    """Scales 1e-10 and 1e3, anisotropy 1e6. float32 cannot hold det(Sigma2d) of a 1e3 Gaussian to the
    reference's accuracy (cancellation in a d - b^2 at ~1e10 px^2), so only finiteness is required."""
    viewmats, Ks = _identity_camera()
    q = torch.tensor([[0.9, 0.3, -0.2, 0.1]]).repeat(4, 1)
    scene = _scene([[0.1, 0.0, 3.0], [0.0, 0.1, 4.0], [-0.2, 0.1, 2.0], [0.2, -0.1, 3.5]],
                   [[1e-10, 1e-10, 1e-10], [1e3, 1e3, 1e3], [1e-3, 1e3, 1.0], [1e-4, 1e2, 1e-4]], quats=q,
                   opacities=[0.9, 0.5, 0.6, 0.7])
    culled = (0,) if rasterize_mode == "antialiased" else ()  # compensation ~ 1e-9 < 1/255
    check_hard_case(scene, viewmats, Ks, 32, 24, culled=culled, compare=False, rasterize_mode=rasterize_mode,
                    what=f"extreme scales {rasterize_mode}")


def test_opacity_extremes_and_max_alpha_clamp():
    """Opacity 0 (culled), exactly 1/255 (at the touch threshold: it can touch only a pixel centre where
    exp(-sigma) = 1), 1 and 0.995 centred on pixel centres, where alpha = o exp(-sigma) exceeds max_alpha
    and is clamped (zero gradient there to o, conic and mean2d; the reference agrees)."""
    viewmats, Ks = _identity_camera()
    fx, cx, cy = (float(Ks[0, 0, 0]), float(Ks[0, 0, 2]), float(Ks[0, 1, 2]))

    def at_pixel(u: int, v: int, z: float) -> list[float]:
        return [(u + 0.5 - cx) / fx * z, (v + 0.5 - cy) / fx * z, z]

    scene = _scene([at_pixel(5, 5, 3.0), at_pixel(16, 14, 3.2), at_pixel(9, 12, 3.1), at_pixel(22, 8, 2.9)],
                   [0.25, 0.25, 0.25], opacities=[0.0, 1.0 / 255.0, 1.0, 0.995])
    check_hard_case(scene, viewmats, Ks, 32, 24, culled=(0,), compare=False, what="opacity extremes")
    # The clamp binds at the two centre pixels (front-most there, so alpha = max_alpha exactly).
    _, alphas, _ = rasterization(*(scene[k] for k in PARAMS), viewmats, Ks, 32, 24)
    assert float(alphas[0, 12, 9, 0]) == float(np.float32(0.99)) == float(alphas[0, 8, 22, 0])
    # Against the reference without the 1/255 Gaussian (its touch decision is knife-edge by design).
    sub = {k: v[[0, 2, 3]] for k, v in scene.items()}
    check_hard_case(sub, viewmats, Ks, 32, 24, culled=(0,), what="max_alpha clamp")


@pytest.mark.slow
def test_ten_thousand_gaussians_on_one_pixel_early_stop():
    """10^4 Gaussians stacked on one pixel: T reaches 1e-4 after a few dozen; those behind the stop get
    exactly zero gradient, the others match the reference."""
    n = 10_000
    g = torch.Generator().manual_seed(5)  # a seed without knife-edge pixels
    width, height = 8, 6
    viewmats, Ks = torch.eye(4)[None], intrinsics(width, height, 60.0)[None]
    z = 2.0 + 2.0 * torch.rand(n, generator=g)
    centre = torch.tensor([4.5 - width / 2, 3.5 - height / 2]) / float(Ks[0, 0, 0])
    means = torch.cat([centre * z[:, None] + 0.002 * torch.randn(n, 2, generator=g), z[:, None]], 1)
    scene = _scene(means, 0.05 * z[:, None].expand(n, 3), opacities=0.3 + 0.4 * torch.rand(n, generator=g),
                   colors=torch.rand(n, 3, generator=g))
    ours, ref = check_hard_case(scene, viewmats, Ks, width, height, what="10^4 on one pixel")
    # Exactly the Gaussians the reference composites somewhere get a gradient; the stop leaves most out.
    reached = (ours["colors"] != 0).any(1)
    assert torch.equal(reached, (ref["colors"] != 0).any(1))
    assert bool((ours["means"][~reached] == 0).all()) and int(reached.sum()) < n // 2, int(reached.sum())


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_jacobian_clamp_far_outside_frustum(rasterize_mode):
    """Far outside the frustum: small ones are culled (off-image), large ones reach into the image with
    their Jacobian clamped (no gradient through the clamped tx/z, ty/z)."""
    viewmats, Ks = _identity_camera()
    scene = _scene([[9.0, 0.0, 3.0], [-3.0, -6.0, 2.0], [4.5, 0.5, 3.0], [-0.5, 3.0, 2.0], [0.2, 0.1, 3.0]],
                   [[0.05, 0.05, 0.05], [0.1, 0.1, 0.1], [3.5, 1.0, 2.0], [1.0, 1.6, 1.0], [0.3, 0.2, 0.2]],
                   quats=torch.tensor([[0.9, 0.1, 0.3, -0.2]]).repeat(5, 1), opacities=[0.9, 0.9, 0.9, 0.8, 0.7])
    grads, _ = check_hard_case(scene, viewmats, Ks, 32, 24, culled=(0, 1), rasterize_mode=rasterize_mode,
                            what=f"far outside {rasterize_mode}")
    assert float(grads["means"][2].abs().sum()) > 0 and float(grads["means"][3].abs().sum()) > 0


def test_exactly_at_jacobian_clamp():
    """Means whose tx/z, ty/z equal the clamp limits as float32 computes them: finite, and the reference
    (torch.clamp passes gradient at its bounds, as the kernel does) agrees."""
    width, height = 32, 24
    viewmats, Ks = _identity_camera(width, height)
    fx, cx, cy = np.float32(Ks[0, 0, 0]), np.float32(Ks[0, 0, 2]), np.float32(Ks[0, 1, 2])
    margin = np.float32(0.15)
    lim_x = (np.float32(width) - cx) / fx + margin * np.float32(width) / fx
    lim_y = cy / fx + margin * np.float32(height) / fx
    z = np.float32(2.0)
    scene = _scene([[float(lim_x * z), 0.1, float(z)], [0.2, float(-lim_y * z), float(z)], [0.0, 0.0, 3.0]],
                   [[0.6, 0.5, 0.4], [0.5, 0.7, 0.3], [0.3, 0.3, 0.3]])
    check_hard_case(scene, viewmats, Ks, width, height, what="at the Jacobian clamp")


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_one_gaussian_covering_the_image(rasterize_mode):
    viewmats, Ks = _identity_camera()
    scene = _scene([[0.1, -0.1, 3.0], [0.0, 0.0, 4.0]], [[5.0, 4.0, 3.0], [0.4, 0.4, 0.4]],
                   quats=[[0.8, 0.2, 0.1, 0.3], [1.0, 0.0, 0.0, 0.0]], opacities=[0.6, 0.9])
    check_hard_case(scene, viewmats, Ks, 32, 24, rasterize_mode=rasterize_mode, what=f"covering {rasterize_mode}")


def test_antialiasing_compensation_tiny_footprints():
    """Sub-pixel Gaussians: the compensation sqrt(det Sigma2d / det Sigma2d') is far below 1 and carries
    most of the gradient to scales."""
    viewmats, Ks = _identity_camera()
    g = torch.Generator().manual_seed(4)
    n = 12
    z = 2.0 + 2.0 * torch.rand(n, generator=g)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 0.9 * z[:, None], z[:, None]], 1)
    scene = _scene(means, 0.004 + 0.01 * torch.rand(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                   opacities=0.6 + 0.4 * torch.rand(n, generator=g))
    check_hard_case(scene, viewmats, Ks, 32, 24, rasterize_mode="antialiased", what="tiny footprints")


def test_unnormalised_and_near_zero_quaternions():
    """Gradients flow through q / |q| for |q| from 1e-12 to 1e3 (d q scales as 1 / |q|); a zero quaternion is
    culled with exact zeros (the reference divides by |q| = 0, so it is checked on its own)."""
    viewmats, Ks = _identity_camera()
    g = torch.Generator().manual_seed(6)
    base = torch.randn(4, 4, generator=g)
    quats = base / base.norm(dim=1, keepdim=True) * torch.tensor([[1e3], [1e-3], [1e-12], [1.0]])
    means = torch.tensor([[0.2, 0.1, 3.0], [-0.3, 0.0, 2.5], [0.0, -0.2, 3.5], [0.3, 0.3, 4.0]])
    scene = _scene(means, [[0.3, 0.1, 0.2]], quats=quats)
    ours, _ = check_hard_case(scene, viewmats, Ks, 32, 24, what="unnormalised quaternions")
    # Rescaling q leaves the image unchanged, so the gradient is tangent to the sphere |q| = const.
    radial = (ours["quats"] * quats.double()).sum(1).abs()
    assert bool((radial <= 1e-5 * ours["quats"].norm(dim=1) * quats.double().norm(dim=1)).all()), radial
    zero = _scene(means, [[0.3, 0.1, 0.2]], quats=torch.cat([torch.zeros(1, 4), quats[1:]]))
    check_hard_case(zero, viewmats, Ks, 32, 24, culled=(0,), compare=False, what="zero quaternion")


@pytest.mark.parametrize("device", DEVICES)
def test_empty_and_all_culled_scenes(device):
    viewmats, Ks = _identity_camera()
    empty = _scene(torch.zeros(0, 3), torch.zeros(0, 3), quats=torch.zeros(0, 4), opacities=torch.zeros(0),
                   colors=torch.zeros(0, 3))
    grads, _ = gradients(rasterization, empty, viewmats, Ks, 32, 24, torch.rand(1, 3), device=device)
    assert grads["means"].shape == (0, 3) and float(grads["backgrounds"].abs().sum()) > 0
    behind = _scene([[0.0, 0.0, -2.0], [0.1, 0.2, -0.5], [5.0, 0.0, 1.0]], [0.3, 0.3, 0.3])
    grads, _ = gradients(rasterization, behind, viewmats, Ks, 32, 24, torch.rand(1, 3), device=device,
                         render_mode="RGB+ED")
    for name in PARAMS:
        assert bool((grads[name] == 0).all()), f"all-culled scene: non-zero gradient of {name}"


@pytest.mark.parametrize("size", [(37, 23), (1, 1), (17, 1)])
def test_image_sizes_not_multiple_of_tile(size):
    width, height = size
    scene = random_scene(20, seed=11, sh_degree=1)
    viewmats, Ks = camera_rig(2, width, height, seed=4)
    check_hard_case(scene, viewmats, Ks, width, height, sh_degree=1, rasterize_mode="antialiased",
                    what=f"{width}x{height}")


# ----------------------------------------------------------------------------------------------------------
# Deterministic mode and tile-size independence
# ----------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
def test_deterministic_gradients_are_reproducible(device):
    """deterministic=True: bit-identical gradients on every run, equal to the atomic ones up to
    summation order, for tile sizes whose tiles are one block (8, 12: not a multiple of 32 threads, 16) or
    several (32, 64). On CPU this runs the same block kernel as on CUDA (Warp's cooperative CPU fibers)."""
    scene = random_scene(60, seed=12, sh_degree=1)
    viewmats, Ks = camera_rig(2, W, H, seed=5)
    kwargs = dict(sh_degree=1, render_mode="RGB+D", rasterize_mode="antialiased", device=device)
    bg = torch.rand(2, 3)
    atomic, _ = gradients(rasterization, scene, viewmats, Ks, W, H, bg, tile_size=16, **kwargs)
    for tile_size in (8, 12, 16, 32, 64):
        runs = []
        for _ in range(2):
            runs.append(gradients(rasterization, scene, viewmats, Ks, W, H, bg, tile_size=tile_size,
                                  deterministic=True, **kwargs)[0])
        for name in runs[0]:
            assert torch.equal(runs[0][name], runs[1][name]), f"tile {tile_size}: {name} differs between runs"
        assert_grads_match(runs[0], atomic, rtol=1e-5, what=f"deterministic vs atomic, tile {tile_size}")
        tiled, _ = gradients(rasterization, scene, viewmats, Ks, W, H, bg, tile_size=tile_size, **kwargs)
        assert_grads_match(tiled, atomic, rtol=1e-5, what=f"atomic tile {tile_size} vs 16")


def test_deterministic_keyword_reaches_the_backward_pass(monkeypatch):
    """The ``deterministic`` keyword of the forward call decides which reduction the backward pass runs."""
    seen = []

    def spy(*args):
        seen.append(args[-1])
        return composite_backward(*args)

    monkeypatch.setattr(autograd, "composite_backward", spy)
    scene = random_scene(30, seed=13)
    viewmats, Ks = camera_rig(1, W, H)
    for flag in (True, False):
        leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
        out, alpha, _ = rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                      leaves["colors"], viewmats, Ks, W, H, deterministic=flag)
        (out.sum() + alpha.sum()).backward()
        assert float(leaves["means"].grad.abs().sum()) > 0
    assert seen == [True, False]
