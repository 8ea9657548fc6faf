"""PSNR and SSIM (sgmodel.metrics.image) against scikit-image on random images, sizes and masks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from sgmodel.metrics.image import has_valid_pixel, image_metrics, psnr, ssim, ssim_map

SK = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)


def sk_ssim(a: np.ndarray, b: np.ndarray, full: bool = False):
    """skimage on one [3, H, W] pair."""
    return structural_similarity(a, b, channel_axis=0, full=full, **SK)


def pair(shape, seed, spread=0.0):
    """Random images; spread > 0 pushes values outside [0, 1] to exercise the clipping."""
    rng = np.random.default_rng(seed)
    a = rng.random(shape) * (1 + 2 * spread) - spread
    b = a + 0.15 * rng.standard_normal(shape)
    return a, b


@pytest.mark.parametrize("hw", [(11, 11), (16, 16), (13, 29), (37, 20), (64, 48)])
def test_ssim_and_psnr_match_skimage(hw):
    a, b = pair((2, 2, 3, *hw), seed=hw[0] * 100 + hw[1], spread=0.1)
    ac, bc = np.clip(a, 0, 1), np.clip(b, 0, 1)
    got = ssim(torch.from_numpy(a), torch.from_numpy(b))
    assert got.shape == (2, 2) and got.dtype == torch.float64
    want = np.array([[sk_ssim(ac[i, j], bc[i, j]) for j in range(2)] for i in range(2)])
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)
    got32 = ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    np.testing.assert_allclose(got32.numpy(), want, rtol=0, atol=2e-6)
    want_psnr = np.array([[peak_signal_noise_ratio(ac[i, j], bc[i, j], data_range=1) for j in range(2)]
                          for i in range(2)])
    np.testing.assert_allclose(psnr(torch.from_numpy(a), torch.from_numpy(b)).numpy(), want_psnr, rtol=1e-12)
    full = np.stack([sk_ssim(ac[0, 1], bc[0, 1], full=True)[1]])
    np.testing.assert_allclose(ssim_map(torch.from_numpy(ac[0, 1]), torch.from_numpy(bc[0, 1])).numpy()[None],
                               full, atol=1e-12)


@pytest.mark.parametrize("hw", [(10, 16), (16, 10), (5, 5), (1, 1)])
def test_ssim_smaller_than_window_raises_like_skimage(hw):
    a, b = pair((3, *hw), seed=0)
    with pytest.raises(ValueError, match="win_size exceeds"):
        sk_ssim(a, b)
    with pytest.raises(ValueError, match="smaller than the 11x11"):
        ssim(torch.from_numpy(a), torch.from_numpy(b))
    assert torch.isfinite(psnr(torch.from_numpy(a), torch.from_numpy(b)))  # PSNR has no window


@pytest.mark.parametrize("hw", [(11, 14), (24, 24), (31, 17)])
def test_masked_metrics_average_the_full_map_over_valid_pixels(hw):
    a, b = (np.clip(x, 0, 1) for x in pair((2, 3, *hw), seed=hw[0] + hw[1]))
    rng = np.random.default_rng(7)
    mask = rng.random((2, 1, *hw)) < 0.6
    mask[1, 0, : hw[0] // 2] = False  # a large invalid block
    got_s = ssim(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask))
    got_p = psnr(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask))
    for i in range(2):
        s_full = sk_ssim(a[i], b[i], full=True)[1]  # [3, H, W]
        m = mask[i, 0]
        assert abs(got_s[i].item() - s_full[:, m].mean()) < 1e-12
        mse = ((a[i] - b[i])[:, m] ** 2).mean()
        assert abs(got_p[i].item() - 10 * np.log10(1 / mse)) < 1e-9
    all_valid = torch.ones(2, 1, *hw, dtype=torch.bool)
    # an all-valid mask gives the full-map mean (borders included) and the unmasked PSNR
    torch.testing.assert_close(psnr(torch.from_numpy(a), torch.from_numpy(b), all_valid),
                               psnr(torch.from_numpy(a), torch.from_numpy(b)))
    s_full = np.mean([sk_ssim(a[i], b[i], full=True)[1].mean() for i in range(1)])
    assert abs(ssim(torch.from_numpy(a[:1]), torch.from_numpy(b[:1]), all_valid[:1]).item() - s_full) < 1e-12


def test_edge_values():
    a, _ = pair((2, 3, 16, 16), seed=3)
    t = torch.from_numpy(a)
    assert torch.all(psnr(t, t) == float("inf"))
    torch.testing.assert_close(ssim(t, t), torch.ones(2, dtype=torch.float64))
    empty = torch.zeros(2, 1, 16, 16, dtype=torch.bool)
    empty[1, 0, 3, 4] = True
    out = image_metrics(t, t.flip(-1), empty)
    assert torch.isnan(out["psnr"][0]) and torch.isnan(out["ssim"][0])
    assert torch.isfinite(out["psnr"][1]) and torch.isfinite(out["ssim"][1]) and "lpips" not in out


def test_a_mask_without_a_valid_pixel_is_found_and_spoils_no_other_image():
    a, b = (torch.from_numpy(np.clip(x, 0, 1)) for x in pair((2, 2, 3, 16, 16), seed=5))
    mask = torch.ones(2, 2, 1, 16, 16, dtype=torch.bool)
    mask[0, 1] = False  # a target whose every pixel is invalid
    mask[1, 0] = False
    mask[1, 0, 0, 0, 0] = True  # one valid pixel left: still defined
    assert has_valid_pixel(mask).tolist() == [[True, False], [True, True]]
    got = image_metrics(a, b, mask)
    for name, value in got.items():
        assert torch.isnan(value[0, 1]) and torch.isfinite(value[has_valid_pixel(mask)]).all(), name
    mse = ((a[1, 0] - b[1, 0])[:, 0, 0] ** 2).mean().item()  # the one valid pixel
    assert got["psnr"][1, 0].item() == pytest.approx(10 * np.log10(1 / mse), abs=1e-9)


def test_bad_shapes_raise():
    x = torch.rand(2, 3, 16, 16)
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, H, W\]"):
        ssim(x, torch.rand(2, 3, 16, 15))
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, H, W\]"):
        psnr(torch.rand(2, 4, 16, 16), torch.rand(2, 4, 16, 16))
    with pytest.raises(ValueError, match="mask must be bool"):
        psnr(x, x, torch.ones(2, 1, 16, 16))
    with pytest.raises(ValueError, match="mask must be bool"):
        ssim(x, x, torch.ones(2, 3, 16, 16, dtype=torch.bool))


def test_ssim_is_differentiable():
    """Autograd's directional derivative against a central finite difference (float64)."""
    a, b = pair((1, 3, 12, 13), seed=5)
    x = torch.from_numpy(a).requires_grad_(True)
    y = torch.from_numpy(b)
    ssim(x, y, clip=False).sum().backward()
    v = torch.from_numpy(np.random.default_rng(6).standard_normal(a.shape))
    h = 1e-6
    with torch.no_grad():
        fd = (ssim(x + h * v, y, clip=False) - ssim(x - h * v, y, clip=False)).sum() / (2 * h)
    assert abs((x.grad * v).sum().item() - fd.item()) < 1e-7 * max(1.0, abs(fd.item()))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ssim_map_without_border_is_the_full_maps_interior(dtype):
    """The training loss's SSIM term filters no padded border (``border=False``): the interior of the full
    map, the same values and gradients up to the convolution's summation order, for images of 11 px (one
    interior pixel) and larger."""
    from sgmodel.metrics.image import SSIM_RADIUS as r
    for shape in ((2, 3, 11, 11), (1, 2, 3, 20, 17)):
        a, b = (torch.from_numpy(x).to(dtype).requires_grad_(True) for x in pair(shape, seed=shape[-1]))
        inner = ssim_map(a, b, border=False)
        full = ssim_map(a, b)[..., r:-r, r:-r]
        assert inner.shape == full.shape
        tol = 1e-13 if dtype == torch.float64 else 1e-5
        torch.testing.assert_close(inner, full, rtol=tol, atol=tol)
        g = torch.randn(inner.shape, dtype=dtype, generator=torch.Generator().manual_seed(0))
        for u, v in zip(torch.autograd.grad(inner, [a, b], g), torch.autograd.grad(full, [a, b], g)):
            torch.testing.assert_close(u, v, rtol=tol, atol=tol)


@pytest.mark.parametrize("case", ["constant", "outside_unit_range", "one_image_constant"])
def test_interior_ssim_backward_is_finite_and_right_on_hard_images(case):
    """The hand-written backward of the loss's SSIM term where its terms degenerate: zero variances
    (D = c2), means of opposite signs (A near 0, which it never divides by), renders outside [0, 1];
    against autograd through the full map (float64)."""
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 3, 16, 14, generator=g, dtype=torch.float64)
    y = torch.rand(2, 3, 16, 14, generator=g, dtype=torch.float64)
    if case == "constant":
        x, y = torch.full_like(x, 0.3), torch.full_like(y, 0.7)
    elif case == "outside_unit_range":
        x, y = x * 3 - 1.5, -y * 0.01
    else:
        y = torch.zeros_like(y)
    from sgmodel.metrics.image import SSIM_RADIUS as r
    xa, ya = x.clone().requires_grad_(True), y.clone().requires_grad_(True)
    xb, yb = x.clone().requires_grad_(True), y.clone().requires_grad_(True)
    ssim_map(xa, ya, border=False).mean().backward()
    ssim_map(xb, yb)[..., r:-r, r:-r].mean().backward()
    for got, want in ((xa.grad, xb.grad), (ya.grad, yb.grad)):
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)
