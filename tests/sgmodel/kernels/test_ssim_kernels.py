"""The Triton interior SSIM (``sgmodel.metrics.image._KernelSSIM``, ``sgmodel.kernels.ssim``: the training loss's SSIM
term on CUDA) against the float64 ``_InteriorSSIM``, which tests/sgmodel/metrics/test_metrics.py checks against autograd
through the full map and skimage. CUDA only (Triton's GPU kernels)."""

from __future__ import annotations

import pytest
import torch

from sgmodel.metrics.image import _InteriorSSIM, _KernelSSIM, ssim_map


def _kernel_ssim_case(shape, layout, case, seed):
    """float64 images x, y [N, 3, H, W] for the Triton SSIM tests; ``layout`` "nhwc": y a permuted view of
    [N, H, W, 3] as the rasteriser's renders are."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    y = (x + 0.15 * torch.randn(shape, generator=g, dtype=torch.float64))
    if case == "constant":
        x, y = torch.full_like(x, 0.3), torch.full_like(y, 0.7)
    elif case == "outside_unit_range":
        x, y = x * 3 - 1.5, -y * 0.01
    elif case == "one_image_zero":
        y = torch.zeros_like(y)
    if layout == "nhwc":
        y = y.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
    return x, y


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (the Triton SSIM kernels)")


@needs_cuda
@pytest.mark.parametrize("shape", [(1, 3, 11, 11), (2, 3, 40, 37), (3, 3, 96, 133), (8, 3, 256, 256)])
@pytest.mark.parametrize("layout", ["nchw", "nhwc"])
@pytest.mark.parametrize("need", [(False, True), (True, False), (True, True), (False, False)])
def test_kernel_ssim_matches_float64_on_cuda(shape, layout, need):
    """The Triton interior SSIM (``_KernelSSIM``, float32) against the float64 ``_InteriorSSIM`` (itself
    tested against autograd through the full map in tests/sgmodel/metrics/test_metrics.py): the map and each gradient, for a
    random gradient map and for the mean (an expanded scalar), within twice the error of PyTorch's float32
    convolutions on the same images; images of one interior pixel up to a batch at the training size, tiles
    cut by the edges, the renders' permuted layout; ``ssim_map`` dispatches float32 CUDA images to it."""
    x, y = _kernel_ssim_case(shape, layout, "random", seed=shape[-1])
    x, y = x.cuda(), y.cuda()

    def run(fn, dtype, upstream):
        """The map, the gradients wanted (of ``upstream`` or of the mean), their strides and the inputs'."""
        xs, ys = (t.detach().to(dtype, copy=True).requires_grad_(n) for t, n in zip((x, y), need))
        s = fn(xs, ys)
        wrt = [t for t, n in zip((xs, ys), need) if n]
        if not wrt:
            return s.double(), [], [], []
        gs = torch.autograd.grad(s, wrt, upstream.to(dtype)) if upstream is not None else \
            torch.autograd.grad(s.mean(), wrt)
        return s.double(), [t.double() for t in gs], [t.stride() for t in gs], [t.stride() for t in wrt]

    grad = torch.randn(shape[0], 3, shape[2] - 10, shape[3] - 10, dtype=torch.float64, device="cuda",
                       generator=torch.Generator("cuda").manual_seed(1))
    for upstream in (grad, None):
        want, want_g, _, _ = run(_InteriorSSIM.apply, torch.float64, upstream)
        base, base_g, _, _ = run(_InteriorSSIM.apply, torch.float32, upstream)
        got, got_g, strides, input_strides = run(_KernelSSIM.apply, torch.float32, upstream)
        assert strides == input_strides  # each gradient laid out as its input
        assert (got - want).abs().max() <= 2 * (base - want).abs().max() + 1e-7
        for gk, gb, gw in zip(got_g, base_g, want_g):
            assert torch.isfinite(gk).all()
            assert (gk - gw).abs().max() <= 2 * (gb - gw).abs().max() + 1e-7 * gw.abs().max()
    xf, yf = x.float(), y.float()
    assert torch.equal(ssim_map(xf, yf, border=False), _KernelSSIM.apply(xf, yf))


@needs_cuda
@pytest.mark.parametrize("case", ["constant", "outside_unit_range", "one_image_zero"])
def test_kernel_ssim_is_finite_and_right_on_hard_images_on_cuda(case):
    """The Triton SSIM where its terms degenerate (zero variances, means of opposite signs, a zero image, values
    outside [0, 1]): finite, and within float32 rounding of the float64 reference."""
    x, y = _kernel_ssim_case((2, 3, 30, 27), "nhwc", case, seed=3)
    x, y = x.cuda(), y.cuda()
    xs, ys = x.clone().requires_grad_(True), y.clone().requires_grad_(True)
    xk, yk = x.float().requires_grad_(True), y.float().requires_grad_(True)
    want = _InteriorSSIM.apply(xs, ys)
    got = _KernelSSIM.apply(xk, yk)
    want.mean().backward()
    got.mean().backward()
    assert torch.isfinite(got).all() and torch.isfinite(xk.grad).all() and torch.isfinite(yk.grad).all()
    torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-4)
    for gk, gw in ((xk.grad, xs.grad), (yk.grad, ys.grad)):
        torch.testing.assert_close(gk.double(), gw, rtol=1e-3, atol=1e-3 * gw.abs().max().item() + 1e-9)
