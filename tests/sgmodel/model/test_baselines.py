"""The baselines without learned prediction (naive-GS, forward-splat) and the depth helpers, on planes at
known depth; expected values from float64 numpy written from SPEC section 7, not from the code under test."""

from __future__ import annotations

import math

import numpy as np
import torch

from sgmodel.model.baselines import forward_splat, naive_gs
from sgmodel.model.geometry import depth_from_disparity, unproject
from sgmodel.model.render import render_views

C0 = 0.28209479177387814


def intrinsics(fx=100.0, fy=110.0, cx=31.3, cy=23.7) -> torch.Tensor:
    return torch.tensor([[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]], dtype=torch.float32)


def texture(h, w, seed=0, smooth=False) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if not smooth:
        return torch.rand(1, 3, h, w, generator=g)
    v, u = np.mgrid[0:h, 0:w] + 0.5
    ph = torch.rand(3, generator=g).numpy() * 6
    img = np.stack([0.5 + 0.3 * np.sin(2 * math.pi * (u / 23 + v / 31) + p) for p in ph])
    return torch.from_numpy(img[None]).float()


def shift_x(t: float) -> torch.Tensor:
    """viewmat [1,1,4,4] of a target camera t metres to the right of the left camera (same orientation)."""
    m = torch.eye(4)
    m[0, 3] = -t
    return m[None, None]


def test_depth_from_disparity_clips_and_marks_invalid():
    d = torch.tensor([4.0, 0.0, -2.0, 1000.0, 1.0]).reshape(1, 1, 1, 5)
    z = depth_from_disparity(d, 100.0, 0.2)
    np.testing.assert_allclose(z.flatten().numpy(), [5.0, 10.0, 10.0, 0.1, 10.0], rtol=1e-6)
    # Middlebury: z = fx B / (d + doffs), per-batch fx and baseline
    z = depth_from_disparity(torch.full((2, 1, 1, 1), 10.0), torch.tensor([100.0, 200.0]),
                             torch.tensor([0.1, 0.05]), doffs=10.0)
    np.testing.assert_allclose(z.flatten().numpy(), [0.5, 0.5], rtol=1e-6)


def test_naive_gs_parameters_follow_the_spec():
    h, w, z0 = 6, 8, 2.5
    K = intrinsics()
    left = texture(h, w)
    z = torch.full((1, 1, h, w), z0)
    z[0, 0, 2, 3] = 0.7
    g = naive_gs(left, z, K)
    Kd = K[0].double().numpy()
    zz = z[0, 0].double().numpy()
    v, u = np.mgrid[0:h, 0:w]
    means = np.stack([zz * (u + 0.5 - Kd[0, 2]) / Kd[0, 0], zz * (v + 0.5 - Kd[1, 2]) / Kd[1, 1], zz], -1)
    s0 = 0.5 * zz / math.sqrt(Kd[0, 0] * Kd[1, 1])
    np.testing.assert_allclose(g["means"][0].numpy(), means.reshape(-1, 3), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(g["scales"][0].numpy(), np.repeat(s0.reshape(-1, 1), 3, 1), rtol=1e-6)
    np.testing.assert_array_equal(g["quats"][0].numpy(), np.tile([1, 0, 0, 0], (h * w, 1)))
    np.testing.assert_allclose(g["opacities"][0].numpy(), 0.99, rtol=1e-7)
    rgb = left[0].double().numpy().reshape(3, -1).T
    np.testing.assert_allclose(g["sh"][0, :, 0].numpy() * C0 + 0.5, rgb, atol=1e-6)
    assert g["sh"].shape == (1, h * w, 9, 3) and not g["sh"][:, :, 1:].any()


def composite_alpha_of_a_pixel_grid(var: float, eps2d: float = 0.3, opacity: float = 0.99) -> float:
    """Float64 alpha at a pixel centre of an infinite grid of equal screen Gaussians of variance ``var``
    px^2 at every pixel centre, "classic" mode as sgmodel renders (SPEC section 2, steps 4, 6, 7)."""
    o = opacity
    transmittance = 1.0
    for i in range(-6, 7):
        for j in range(-6, 7):
            a = o * math.exp(-0.5 * (i * i + j * j) / (var + eps2d))
            if a >= 1 / 255:
                transmittance *= 1 - min(a, 0.99)
    return 1 - transmittance


def test_naive_gs_rendered_from_the_left_camera_reproduces_the_left_image():
    """The render reproduces a smooth left image; the coverage is that of half-pixel footprints
    (s0 = 0.5 z / f projects to a 0.5 px standard deviation, plus the 0.3 px^2 low-pass)."""
    h, w = 40, 48
    K = intrinsics(fx=100.0, fy=100.0, cx=24.0, cy=20.0)
    left = texture(h, w, smooth=True)
    g = naive_gs(left, torch.full((1, 1, h, w), 3.0), K)
    rgb, alpha = render_views(g, torch.eye(4)[None, None], K[:, None], w, h)
    inner = (slice(None), slice(3, -3), slice(3, -3))
    expected = composite_alpha_of_a_pixel_grid(0.25)    # on the axis; off it, the footprint grows slowly
    assert expected > 0.99
    np.testing.assert_allclose(alpha[0, 0, 18:22, 22:26].numpy(), expected, atol=1e-3)
    assert expected - 1e-3 < alpha[0, 0][inner].min() and alpha[0, 0][inner].max() < expected + 0.015
    err = (rgb[0, 0] - left[0])[inner]
    psnr = -10 * math.log10(float((err ** 2).mean()))
    assert psnr > 25, psnr                                # the overlap of neighbours blurs a little


def test_forward_splat_shifts_a_plane_by_fx_t_over_z():
    h, w, fx, z0, t = 12, 20, 100.0, 2.0, 0.08          # fx t / z = 4 pixels exactly
    K = intrinsics(fx=fx, cx=9.6)
    left = texture(h, w, seed=1)
    img, cov = forward_splat(left, torch.full((1, 1, h, w), z0), K, shift_x(t), K[:, None], w, h)
    shift = round(fx * t / z0)
    np.testing.assert_array_equal(img[0, 0, :, :, : w - shift].numpy(), left[0, :, :, shift:].numpy())
    expected_cov = np.zeros((h, w), bool)
    expected_cov[:, : w - shift] = True
    np.testing.assert_array_equal(cov[0, 0, 0].numpy(), expected_cov)
    assert not img[0, 0, :, :, w - shift:].any()             # holes stay empty


def test_forward_splat_z_buffer_keeps_the_nearer_of_two_planes():
    h, w, fx, t = 10, 24, 100.0, 0.08
    K = intrinsics(fx=fx, cx=12.0)
    left = texture(h, w, seed=2)
    z = torch.full((1, 1, h, w), 4.0)                    # background: shifts by 2 px
    z[..., 2:8, 8:14] = 2.0                              # a nearer square: shifts by 4 px
    img, cov = forward_splat(left, z, K, shift_x(t), K[:, None], w, h)
    # painter's algorithm, far to near, from the known shifts
    expected = np.zeros((3, h, w))
    covered = np.zeros((h, w), bool)
    src, zz = left[0].numpy(), z[0, 0].numpy()
    for depth, shift in ((4.0, 2), (2.0, 4)):
        for v, u in zip(*np.nonzero(zz == depth)):
            if u - shift >= 0:
                expected[:, v, u - shift] = src[:, v, u]
                covered[v, u - shift] = True
    np.testing.assert_array_equal(img[0, 0].numpy(), expected.astype(np.float32))
    np.testing.assert_array_equal(cov[0, 0, 0].numpy(), covered)
    assert covered[2:8, 4:10].all() and not covered[2:8, 10:12].any()   # square, then the disocclusion hole


def test_forward_splat_batches_and_targets_are_independent():
    h, w = 8, 12
    K = intrinsics(fx=50.0, cx=6.0, cy=4.0)
    left = torch.cat([texture(h, w, seed=3), texture(h, w, seed=4)])
    z = torch.full((2, 1, h, w), 2.5)
    views = torch.cat([shift_x(0.1), shift_x(-0.1)], dim=1).expand(2, 2, 4, 4)
    Ks = K[:, None].expand(2, 2, 3, 3)
    img, cov = forward_splat(left, z, K.expand(2, 3, 3), views, Ks, w, h)
    for b in range(2):
        for t in range(2):
            one, c1 = forward_splat(left[b:b + 1], z[b:b + 1], K, views[b:b + 1, t:t + 1], Ks[:1, :1], w, h)
            assert torch.equal(img[b, t], one[0, 0]) and torch.equal(cov[b, t], c1[0, 0])
    assert torch.equal(unproject(z, K.expand(2, 3, 3))[0], unproject(z[:1], K)[0])
