"""Degenerate and extreme inputs for the Warp rasteriser (float32 in): never NaN or Inf, always the reference.

Every case goes through ``render_both`` + ``assert_matches_reference`` (tests/support/scenes.py), which checks that
no output (colours, alphas, floating meta tensors) is NaN/Inf and holds the image to the float64 reference.
Most cases use the identity camera (zero translation): camera depths are then the float32 inputs
themselves, exact in both arithmetics, and the intrinsics below put pixel centres at exactly representable
screen positions, so the cases that sit *on* a threshold (opacity 1/255 at a pixel centre, two opaque
Gaussians meeting the 1e-4 stop) are decided identically by float32 and float64 and are asserted exactly;
see each test for why.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.support.scenes import assert_finite, assert_matches_reference, camera_rig, random_scene, render_both

# 17x13 image (no multiple of any tile size), f = 16 px, principal point on the centre of pixel (8, 6).
# With depth z = 2, a mean at (k / 8, l / 8, 2) projects exactly onto the centre of pixel (8 + k, 6 + l).
W, H, F = 17, 13, 16.0
K = torch.tensor([[[F, 0.0, 8.5], [0.0, F, 6.5], [0.0, 0.0, 1.0]]])
EYE = torch.eye(4)[None]
MODES = ["classic", "antialiased"]


def _scene(means, scales, opacities, quats=None, colors=None, sh_degree: int | None = None) -> dict:
    """float32 scene dict from lists; identity rotations and distinct colours unless given."""
    n = len(means)
    g = torch.Generator().manual_seed(n)
    if colors is None:
        colors = (torch.rand(n, 3, generator=g) if sh_degree is None
                  else 0.5 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g))
    scene = {
        "means": torch.as_tensor(means, dtype=torch.float32).reshape(n, 3),
        "quats": torch.as_tensor([[1.0, 0.0, 0.0, 0.0]] * n if quats is None else quats, dtype=torch.float32
                                 ).reshape(n, 4),
        "scales": torch.as_tensor(scales, dtype=torch.float32).reshape(n, 3),
        "opacities": torch.as_tensor(opacities, dtype=torch.float32).reshape(n),
        "colors": torch.as_tensor(colors, dtype=torch.float32),
    }
    return scene


def _check(scene: dict, viewmats=EYE, Ks=K, width: int = W, height: int = H, exact_depths: bool = False,
           **kw) -> tuple:
    """Render both ways (RGB+ED over a grey background unless told), check finiteness and agreement."""
    kw.setdefault("render_mode", "RGB+ED")
    if "RGB" in kw["render_mode"]:
        kw.setdefault("backgrounds", torch.full((viewmats.shape[0], scene["colors"].shape[-1]), 0.25))
    ours, ref = render_both(scene, viewmats, Ks, width, height, **kw)
    assert_matches_reference(ours, ref, kw["render_mode"], exact_depths=exact_depths)
    return ours, ref


def _quat(axis, angle_deg: float) -> list[float]:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    h = math.radians(angle_deg) / 2
    return [math.cos(h), *(math.sin(h) * a)]


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_near_plane_and_camera_centre(rasterize_mode: str) -> None:
    """Behind the camera, exactly on the near plane (culled: z <= near), one float32 step in front of it
    (a huge splat), straddling it (centre in front, extent behind), at the camera centre (SH direction
    mean - camera = 0 must not leak a NaN: it is culled), and one ordinary Gaussian. Depths are exact
    float32 values under the identity camera, so the near-plane comparisons are exact in both arithmetics."""
    near = 0.25
    just_in_front = float(np.nextafter(np.float32(near), np.float32(1)))  # 0.25 + 3e-8
    means = [[0, 0, -1], [0.1, 0, near], [0.05, 0.02, just_in_front], [-0.2, 0.1, 0.5], [0, 0, 0], [0.25, 0, 2]]
    scales = [[0.3] * 3, [0.05] * 3, [0.05] * 3, [0.4, 0.3, 0.6], [0.2] * 3, [0.1] * 3]
    scene = _scene(means, scales, [0.9, 0.9, 0.5, 0.6, 0.9, 0.8], sh_degree=1)
    ours, ref = _check(scene, sh_degree=1, near_plane=near, rasterize_mode=rasterize_mode, exact_depths=True)
    assert ref[2]["visible"][0].tolist() == [False, False, True, True, False, True]
    assert float(ref[1].min()) > 0.1  # the straddling and the just-in-front Gaussians cover the image


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_extreme_scales(rasterize_mode: str) -> None:
    """Scale 1e-10 (on and off pixel centres; classic: alpha = o at the centre it sits on, antialiased: the
    compensation ~ (f s / z)^2 / 0.3 ~ 1e-17 hides it), a 1e-10 x 1e-10 x 0.3 needle along the viewing
    ray's depth (a rank-1 screen covariance: det(Sigma2d) is pure rounding, ~1e-9 in float32, so its
    antialiased compensation stays ~1e-4 and it is invisible both ways) and scale 1e3 (covers the whole
    image: sigma ~ 1e-5 at the corners, alpha ~ o everywhere, far from any threshold)."""
    means = [[0, 0, 2], [0.125, -0.25, 2], [-0.9, 0.6, 3], [0.0, 0.0, 5.0]]
    scales = [[1e-10] * 3, [1e-10] * 3, [1e-10, 1e-10, 0.3], [1e3] * 3]
    scene = _scene(means, scales, [0.8, 0.5, 0.9, 0.6])
    ours, ref = _check(scene, rasterize_mode=rasterize_mode, exact_depths=True)
    assert float(ref[1].min()) > 0.5
    if rasterize_mode == "classic":  # 1 - (1 - 0.8)(1 - 0.6 exp(-tiny)) on the tiny Gaussian's pixel
        assert float(ours[1][0, 6, 8, 0]) == pytest.approx(1 - 0.2 * 0.4, abs=1e-5)


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_anisotropy_1e6(rasterize_mode: str) -> None:
    """Needles and discs with a 1e6 scale ratio. On the optical axis with axis-aligned orientation the
    screen covariance stays diagonal (b = 0 exactly), so det(Sigma2d) has no cancellation and the
    antialiased compensation is well conditioned. An oblique needle's det(Sigma2d) = a c - b^2 is a float32
    cancellation (its true value ~1e-10, float32 error up to ~6e-5): in classic mode it does not matter
    (eps2d dominates the conic), in antialiased mode the compensation sqrt(det / det') is 0 in float64 and
    at most ~5e-3 in float32, so with opacity 0.5 the needle stays below 1/255 both ways (invisible)."""
    means = [[0, 0, 3], [0, 0, 4], [0, 0, 2.5], [0.1, -0.1, 3.5], [0, 0, 6]]
    scales = [[0.5, 5e-7, 5e-7], [5e-7, 0.4, 5e-7], [0.3, 0.3, 3e-7], [0.5, 5e-7, 5e-7], [3e-7, 0.5, 0.5]]
    quats = [[1, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0], _quat([0.3, 1, 0.2], 50), [1, 0, 0, 0]]
    scene = _scene(means, scales, [0.9, 0.8, 0.7, 0.5, 0.6], quats=quats)
    ours, ref = _check(scene, rasterize_mode=rasterize_mode, exact_depths=True)
    if rasterize_mode == "antialiased":
        assert float(ref[2]["opacities"][0, 3]) < 1 / 255  # the oblique needle is invisible in float64


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_opacity_zero_exactly_1_over_255_and_one(rasterize_mode: str) -> None:
    """Small Gaussians (Sigma2d = 0.04 px^2) each exactly on a pixel centre (sigma = 0 in both
    arithmetics; neighbours have sigma >= 1.4, far below 1/255).

    float32 cannot hold 1/255: float32(1/255) = 1/255 + 2.3e-10 touches in float64 (>= 1/255) and in
    float32 (== the float32 threshold); the next float32 below it is 1/255 - 2.3e-10 and touches in
    neither. So the touch threshold lies between two adjacent float32 values in both arithmetics and the
    outcome is exact: asserted directly (the generic comparison would call these pixels knife-edge).
    Opacity 1 saturates at max_alpha. Two opaque Gaussians on one pixel: T (1 - alpha) after the second is
    (1 - float32(0.99))^2 = 9.99998e-5 <= 1e-4: the second is not composited (alpha stays 0.99). In float64
    with 0.99 itself it would be 1.0000000000000002e-4 > 1e-4, which is why the reference is given the
    float32 max_alpha (``render_both``); margin 1.9e-6 relative, far above float32 rounding of one product.
    """
    o255 = float(np.float32(1 / 255))
    o255_below = float(np.nextafter(np.float32(1 / 255), np.float32(0)))
    assert o255 > 1 / 255 > o255_below
    s = 0.2 * 2 / F  # f s / z = 0.2 px at z = 2 (and 1.5 s at z = 3)
    # (row, col) of pixel centres: mean (k/8, l/8, 2) -> (6 + l, 8 + k); (0.75, 0.375, 3) -> (8, 12) too.
    means = [[-0.5, -0.5, 2], [-0.25, -0.5, 2], [0, -0.5, 2], [0.25, -0.5, 2], [0.5, 0.25, 2], [0.75, 0.375, 3]]
    scales = [[s] * 3] * 5 + [[1.5 * s] * 3]
    scene = _scene(means, scales, [0.0, o255, o255_below, 1.0, 1.0, 1.0])
    ours, ref = render_both(scene, EYE, K, W, H, render_mode="RGB+D", rasterize_mode=rasterize_mode,
                            backgrounds=torch.zeros(1, 3))
    assert_finite(ours)
    # Opacity-1 Gaussians touch their 3x3 block (o' exp(-d^2 / 0.68) >= 1/255 for d^2 <= 2, classic and
    # antialiased alike: o' = 1 or ~0.04 / 0.34); the float32(1/255) one only its own pixel, in classic mode.
    expect_touched = torch.zeros(H, W, dtype=torch.bool)
    expect_touched[1:4, 9:12] = True
    expect_touched[7:10, 11:14] = True
    expect_touched[2, 6] = rasterize_mode == "classic"
    for out in (ours, ref):
        alpha = out[1][0, ..., 0].double()
        assert torch.equal(alpha > 0, expect_touched)
        if rasterize_mode == "classic":
            assert float(alpha[2, 10]) == pytest.approx(float(np.float32(0.99)), abs=1e-7)  # max_alpha binds
            assert float(alpha[8, 12]) == pytest.approx(float(np.float32(0.99)), abs=1e-7)  # the second stops
            assert float(alpha[2, 6]) == pytest.approx(o255, rel=1e-6)
    torch.testing.assert_close(ours[0].double(), ref[0], rtol=0, atol=1e-5)
    torch.testing.assert_close(ours[1].double(), ref[1], rtol=0, atol=1e-6)


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_faint_gaussian_expected_depth(rasterize_mode: str) -> None:
    """A lone faint Gaussian (alpha <= 0.02 everywhere, >= 1/255 where it touches): "ED" = D / alpha is its
    depth exactly wherever alpha > 0, which a floor on alpha larger than 1/255 would break."""
    scene = _scene([[0.1, -0.05, 2.5]], [[0.3, 0.2, 0.1]], [0.02], quats=[_quat([0, 0, 1], 30)])
    ours, ref = _check(scene, render_mode="ED", rasterize_mode=rasterize_mode, exact_depths=True)
    for out in (ours, ref):
        touched = out[1][0, ..., 0] > 0
        assert int(touched.sum()) > 10
        torch.testing.assert_close(out[0][0, ..., 0][touched].double(), torch.full((int(touched.sum()),), 2.5,
                                   dtype=torch.float64), rtol=1e-5, atol=0)


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_ten_thousand_gaussians_on_one_pixel(rasterize_mode: str) -> None:
    """10^4 Gaussians on the optical axis (all centred on pixel (4, 3) of a 9x7 image), depths in [1, 10]
    with 500 exact depth ties in front (order by index; twins of opposite colours), Sigma2d = 0.25 px^2:
    the early stop ends the centre pixel after ~30 and its neighbours later. Depths are exact float32
    inputs (identity camera), so the order is the same in both arithmetics; opacities are chosen so that
    o' exp(-sigma) stays clear of 1/255 at every pixel distance (d^2 = 4 touches, d^2 = 5 does not); the
    reference's margins confirm no knife-edge."""
    n = 10_000
    g = torch.Generator().manual_seed(2)
    z = 1.0 + 9.0 * torch.rand(n, generator=g)
    z[:500] = 1.0 + 0.5 * torch.rand(500, generator=g)  # in front, where the order shows
    z[-500:] = z[:500]  # exact ties with lower-index twins of the opposite colour
    colors = torch.rand(n, 3, generator=g)
    colors[-500:] = 1.0 - colors[:500]
    means = torch.stack([torch.zeros(n), torch.zeros(n), z], -1)
    scales = (0.5 * z / F)[:, None].repeat(1, 3)
    lo, hi = (0.2, 0.35) if rasterize_mode == "classic" else (0.45, 0.75)  # o' = o * 0.25 / 0.55 antialiased
    opac = lo + (hi - lo) * torch.rand(n, generator=g)
    scene = _scene(means, scales, opac, colors=colors)
    K9 = torch.tensor([[[F, 0.0, 4.5], [0.0, F, 3.5], [0.0, 0.0, 1.0]]])
    ours, ref = _check(scene, Ks=K9, width=9, height=7, rasterize_mode=rasterize_mode, exact_depths=True)
    meta = ref[2]
    assert 10 < int(meta["n_composited"][0, 3, 4]) < 60  # stopped early: far fewer than 10^4
    assert float(meta["touch_margin"].min()) > 1e-2 and float(meta["stop_margin"].min()) > 1e-4
    # The stop leaves T in (1e-4, 1e-4 / (1 - alpha)) with alpha <= 0.35 here.
    for out in (ours, ref):
        assert 1 - 1e-4 / 0.65 < float(out[1][0, 3, 4, 0]) < 1 - 1e-4


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_far_outside_the_frustum(rasterize_mode: str) -> None:
    """Gaussians at tx/z, ty/z far beyond the widened field of view (SPEC step 3 clamps the Jacobian there):
    big ones whose footprint still reaches into the image, small ones that touch nothing, one at 1e3 x the
    field of view. Camera depths are exact (identity camera)."""
    z = 2.0
    means = [[5 * z, 0, z], [-6 * z, 0.5, z], [0, 4 * z, z], [3 * z, -3 * z, z], [20 * z, 0, z], [0, -30 * z, z],
             [600.0, 0.0, 0.3]]
    scales = [[2.0 * z] * 3, [2.5 * z] * 3, [2.0 * z] * 3, [2.2 * z] * 3, [0.1] * 3, [0.1] * 3, [50.0] * 3]
    scene = _scene(means, scales, [0.7, 0.6, 0.8, 0.5, 0.9, 0.9, 0.9])
    ours, ref = _check(scene, rasterize_mode=rasterize_mode, exact_depths=True)
    assert float(ref[1].max()) > 0.05  # the clamped big ones reach in


@pytest.mark.parametrize("rasterize_mode", MODES)
def test_one_gaussian_covers_the_image(rasterize_mode: str) -> None:
    scene = _scene([[0.1, -0.05, 4.0]], [[8.0, 6.0, 3.0]], [0.7], quats=[_quat([1, 2, 3], 40)])
    ours, ref = _check(scene, rasterize_mode=rasterize_mode, exact_depths=True)
    assert float(ref[1].min()) > 0.6


@pytest.mark.parametrize("sh_degree", [None, 3])
def test_empty_and_all_culled(sh_degree: int | None) -> None:
    """N = 0, and N = 3 all culled (behind, on the camera centre, beyond far): background only, alpha 0,
    depth 0, expected depth 0 (0 / max(0, 1e-10))."""
    empty = {"means": torch.zeros(0, 3), "quats": torch.zeros(0, 4), "scales": torch.zeros(0, 3),
             "opacities": torch.zeros(0), "colors": torch.zeros(0, 3) if sh_degree is None else torch.zeros(0, 16, 3)}
    culled = _scene([[0, 0, -2], [0, 0, 0], [0, 0, 50]], [[0.5] * 3] * 3, [0.9] * 3, sh_degree=sh_degree)
    bg = torch.tensor([[0.1, 0.2, 0.3]])
    for scene in (empty, culled):
        for mode in ("RGB+ED", "D"):
            ours, ref = _check(scene, sh_degree=sh_degree, far_plane=10.0, render_mode=mode,
                               backgrounds=bg if mode == "RGB+ED" else None)
            assert bool((ours[1] == 0).all())
            assert bool((ours[0][..., -1] == 0).all())
            if mode == "RGB+ED":
                assert bool((ours[0][..., :3] == bg[0]).all())


@pytest.mark.parametrize("width,height,tile_size", [(1, 1, 16), (1, 1, 8), (1, 9, 16), (13, 1, 8), (33, 17, 16),
                                                     (35, 29, 32)])
def test_image_sizes(width: int, height: int, tile_size: int) -> None:
    """1x1 images, single rows and columns, and sizes that are no multiple of the tile size."""
    scene = random_scene(120, seed=width * 100 + height, sh_degree=1, scale=(0.1, 1.0))
    viewmats, Ks = camera_rig(2, width, height, seed=6)
    _check(scene, viewmats=viewmats, Ks=Ks, width=width, height=height, sh_degree=1, tile_size=tile_size,
           rasterize_mode="antialiased")
