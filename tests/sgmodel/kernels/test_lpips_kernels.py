"""LPIPS's tap distance on CUDA (``sgmodel.metrics.lpips._KernelTapDistance``, the Triton kernels of
``sgmodel.kernels.lpips_tap``) against the float64 ``_TapDistance`` (itself checked against autograd through the
plain operations in tests/sgmodel/metrics/test_lpips.py), and the LPIPS term built on it against the PyTorch path. The
kernels run where tests/support/kernels.py says; the dispatch and the LPIPS term on CUDA only (the CPU's path is
``_TapDistance``, tested there)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from sgmodel.metrics import lpips as lpips_module
from sgmodel.metrics.lpips import _KernelTapDistance, _TapDistance, random_lpips, tap_distance
from tests.support.kernels import KERNEL_DEVICE, interpret_only_if, kernel_test

CL = torch.channels_last
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (the Triton tap-distance kernels)")
#: a gradient written in the feature's dtype is within one of its roundings of the float64 one: relative, and
#: the spacing of its subnormals (float16's start at 6e-5: a mean's gradient reaches them).
ROUNDING = {torch.float32: (2e-6, 0.0), torch.bfloat16: (2 ** -8, 0.0), torch.float16: (2 ** -11, 2 ** -24)}


def features(n, c, h, w, layout, dtype, seed, zero_pixels=True):
    """ReLU-like features a, b [n, c, h, w] on ``KERNEL_DEVICE`` in ``dtype`` and ``layout`` ("channels_last",
    "nchw", or "slice": a channel slice of a wider channels-last map); with ``zero_pixels`` some pixels all zero on one
    side and one on both (ReLU outputs have them), else none."""
    g = torch.Generator().manual_seed(seed)
    a, b = (torch.relu(torch.randn(n, c + (3 if layout == "slice" else 0), h, w, generator=g)) for _ in range(2))
    b = torch.where(torch.rand(b.shape, generator=g) < 0.5, a + 0.1 * b, b)  # half the channels near a's
    if not zero_pixels:  # none by chance either (a pixel of 3 channels is all zero one time in 8)
        a, b = a + 0.05, b + 0.05
    else:
        a[0, :, 0, 0] = 0
        b[-1, :, h - 1, w - 1] = 0
        a[0, :, h // 2, w // 2] = b[0, :, h // 2, w // 2] = 0
    out = []
    for t in (a, b):
        t = t.to(KERNEL_DEVICE, dtype)
        if layout != "nchw":
            t = t.contiguous(memory_format=CL)
        out.append(t[:, 1:c + 1] if layout == "slice" else t)
    return out


@kernel_test
@pytest.mark.parametrize("shape", [(1, 64, 1, 1), (2, 64, 9, 13), (3, 100, 7, 5), (2, 3, 6, 6), (1, 512, 8, 8),
                                   (4, 128, 32, 32)])
@pytest.mark.parametrize("layout", ["channels_last", "nchw", "slice"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
@pytest.mark.parametrize("need", [(False, True), (True, False), (True, True), (False, False)])
def test_tap_distance_kernels_match_float64(shape, layout, dtype, need):
    """The map and each gradient wanted, for a random and an expanded (a mean's) incoming gradient: the map
    within float32 rounding of the float64 one on the same feature values, each gradient within one rounding
    of its dtype, in the feature's dtype and memory format (a channel slice's: dense channels-last); all-zero
    feature pixels included (their gradient
    is the 1 / eps one of ``_TapDistance``, beyond float16's range: float16 cases have none)."""
    interpret_only_if(dtype == torch.float32, "the interpreter's half-precision arithmetic is not the GPU's")
    a, b = features(*shape, layout, dtype, seed=shape[1] + shape[2], zero_pixels=dtype != torch.float16)
    w = torch.rand(1, shape[1], 1, 1, generator=torch.Generator().manual_seed(2)).to(KERNEL_DEVICE)
    n, _, h, wd = shape
    up = torch.rand(n, 1, h, wd, generator=torch.Generator().manual_seed(3), dtype=torch.float64).to(KERNEL_DEVICE)
    for upstream in (up, None):
        results = []
        for fn, xs in ((_KernelTapDistance.apply, (a, b)), (_TapDistance.apply, (a.double(), b.double()))):
            xs = [x.detach().requires_grad_(nd) for x, nd in zip(xs, need)]
            d = fn(*xs, w.to(torch.promote_types(xs[0].dtype, torch.float32)))
            wrt = [x for x, nd in zip(xs, need) if nd]
            grads = [] if not wrt else torch.autograd.grad(d, wrt, upstream.to(d.dtype)) if upstream is not None \
                else torch.autograd.grad(d.mean(), wrt)
            results.append((d, grads))
        (got, got_g), (want, want_g) = results
        assert got.dtype == torch.float32 and got.shape == (n, 1, h, wd)
        torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-6 * want.abs().max().item())
        fmt = torch.contiguous_format if layout == "nchw" else CL
        grad = upstream if upstream is not None else torch.full_like(want, 1 / want.numel())
        sides = [(f, o) for f, o, nd in ((a, b, need[0]), (b, a, need[1])) if nd]
        for g, gw, (f, o) in zip(got_g, want_g, sides):
            assert g.dtype == dtype and g.is_contiguous(memory_format=fmt)
            assert torch.isfinite(g).all()
            err, scale = (g.double() - gw).abs(), first_term(f.double(), o.double(), w.double(), grad)
            rel, tiny = ROUNDING[dtype]
            assert (err <= rel * gw.abs() + tiny + 1e-5 * scale).all(), (err / scale).max().item()


def first_term(f, o, w, grad):
    """Per pixel, the size of the terms of the gradient's first term, 2 |grad| max_c w_c (|u_f,c| + |u_o,c|) / n_f
    (u = f / n_f): float32's cancellations in h = w (u_f - u_o) (features alike on both sides) and in
    g = (h - f (h . f) / (n_f |f|)) 2 grad / n_f are relative to it, not to g."""
    norm = [torch.linalg.vector_norm(t, dim=1, keepdim=True) + 1e-10 for t in (f, o)]
    size = w * ((f / norm[0]).abs() + (o / norm[1]).abs())
    return 2 * grad.abs() * size.amax(dim=1, keepdim=True) / norm[0]


@kernel_test
def test_tap_distance_of_identical_features_vanishes():
    """The same features on both sides (a render equal to its target): the map and the gradient vanish up to
    float32's rounding of the difference of the two (equal) normalisations (the compiler may contract one
    product into a fused multiply-add), and are exactly 0 at all-zero pixels."""
    a, _ = features(2, 64, 5, 6, "channels_last", torch.bfloat16, seed=1)
    b = a.clone().requires_grad_(True)
    w = torch.rand(1, 64, 1, 1, device=KERNEL_DEVICE)
    d = tap_distance(a, b, w)
    (g,) = torch.autograd.grad(d.sum(), b)
    assert (d.abs() <= 1e-12).all(), d.abs().max().item()
    scale = first_term(b.double(), a.double(), w.double(), torch.ones_like(d, dtype=torch.float64))
    assert (g.double().abs() <= 1e-6 * scale).all()
    zero = a.abs().sum(dim=1, keepdim=True) == 0
    assert zero.sum() == 2 and (d[zero] == 0).all() and (g * zero == 0).all()


@needs_cuda
def test_tap_distance_dispatches_to_the_kernels_on_cuda(monkeypatch):
    """CUDA features of float32, float16 or bfloat16 take the kernels; float64 and the CPU take
    ``_TapDistance``, and so do features wider than the kernels' tiles hold."""
    w = torch.rand(1, 8, 1, 1, device="cuda")
    for dtype, kernel in ((torch.float32, True), (torch.bfloat16, True), (torch.float16, True),
                          (torch.float64, False)):
        a = torch.rand(1, 8, 2, 2, device="cuda", dtype=dtype, requires_grad=True)
        name = type(tap_distance(a, a.detach(), w).grad_fn).__name__
        assert ("_KernelTapDistance" in name) == kernel, (dtype, name)
    a = torch.rand(1, 8, 2, 2, requires_grad=True)
    assert "_KernelTapDistance" not in type(tap_distance(a, a.detach(), w.cpu()).grad_fn).__name__
    monkeypatch.setattr(lpips_module, "_KERNEL_MAX_CHANNELS", 4)
    a = torch.rand(1, 8, 2, 2, device="cuda", requires_grad=True)
    assert "_KernelTapDistance" not in type(tap_distance(a, a.detach(), w).grad_fn).__name__


@needs_cuda
@pytest.mark.parametrize("amp", [True, False])
def test_lpips_term_with_the_kernels_matches_the_pytorch_path_on_cuda(amp, monkeypatch):
    """The LPIPS term (random VGG16, the real linear layers) with the kernels against the same with
    ``_TapDistance`` on CUDA, in the bf16 training path and in float32: the value and the render's gradient
    agree to the features' rounding (the same features: only the distance's arithmetic differs)."""
    net = random_lpips("cuda")
    g = torch.Generator(device="cuda").manual_seed(5)
    target = torch.rand(8, 3, 64, 64, device="cuda", generator=g)
    render = (target + 0.05 * torch.randn(target.shape, device="cuda", generator=g)).clamp(0, 1).requires_grad_(True)
    results = []
    for kernels in (True, False):
        monkeypatch.setattr(lpips_module, "_kernel_runs", (lambda a, b: True) if kernels else (lambda a, b: False))
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp), \
                torch.backends.cudnn.flags(enabled=True, allow_tf32=amp):  # float32: VGG16's backward too
            value = net(target, render).float().mean()
            (grad,) = torch.autograd.grad(value, render)
        results.append((value, grad))
    (got, g_got), (want, g_want) = results
    torch.testing.assert_close(got, want, rtol=1e-5, atol=0)
    rel = ((g_got - g_want).norm() / g_want.norm()).item()
    assert rel < (5e-3 if amp else 1e-5), rel
    assert F.cosine_similarity(g_got.flatten(), g_want.flatten(), dim=0) > (0.9999 if amp else 0.999999)
