"""``layers.cat_channels`` with edge replication (``pads``): on the CPU the padding and ``torch.cat``, on CUDA
the Triton kernels of ``sgmodel.kernels.concat``; both against a float64 reference written here from the
definition (each output pixel reads the source pixel at clamped coordinates; gradients by autograd through
that gather)."""

from __future__ import annotations

import copy

import pytest
import torch

from sgmodel.config import PredictorParams
from sgmodel.model import decoder as decoder_module
from sgmodel.model import predictor as predictor_module
from sgmodel.model.layers import cat_channels
from sgmodel.model.predictor import GaussianPredictor
from tests.support.kernels import KERNEL_DEVICE, kernel_test
from tests.support.model_helpers import layers_case

CL = torch.channels_last
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (the Triton concat kernels)")


def reference(tensors, pads, width, biases=None):
    """float64 [B, width, Hd, Wd]: each tensor read at (clamp(y - p), clamp(x - p)) plus its bias (if any),
    concatenated, then one channel of ones and zeros up to ``width``."""
    Hd, Wd = tensors[0].shape[2] + 2 * pads[0], tensors[0].shape[3] + 2 * pads[0]
    parts = []
    for t, p, b in zip(tensors, pads, biases or [None] * len(tensors)):
        iy = (torch.arange(Hd, device=t.device) - p).clamp(0, t.shape[2] - 1)
        ix = (torch.arange(Wd, device=t.device) - p).clamp(0, t.shape[3] - 1)
        read = t.double()[:, :, iy][:, :, :, ix]
        parts.append(read if b is None else read + b.double()[None, :, None, None])
    total = sum(t.shape[1] for t in tensors)
    if width > total:
        spare = torch.zeros(tensors[0].shape[0], width - total, Hd, Wd, dtype=torch.float64, device=tensors[0].device)
        spare[:, 0] = 1
        parts.append(spare)
    return torch.cat(parts, 1)


def _case(B, size, p, channels, layouts, dtype, device, seed=0):
    """Sources: the first at the output's size, ``size`` + 2p (no padding), the rest at ``size``, padded by p."""
    g = torch.Generator().manual_seed(seed)
    H, W = size
    out = []
    for k, (C, layout) in enumerate(zip(channels, layouts)):
        h, w = (H + 2 * p, W + 2 * p) if k == 0 else (H, W)
        t = torch.randn(B, C, h, w, generator=g, dtype=torch.float64)
        if layout == "slice":  # a channel slice of a wider channels-last tensor: strides of its own
            t = torch.randn(B, C + 3, h, w, generator=g, dtype=torch.float64).contiguous(memory_format=CL)[:, 1:C + 1]
        elif layout == "cl":
            t = t.contiguous(memory_format=CL)
        out.append(t.to(device=device, dtype=dtype))
    return out, [0] + [p] * (len(channels) - 1)


CASES = [  # batch, size of the sources that are padded, padding, channels, layouts, appended multiple
    (2, (5, 7), 2, (3, 1, 70), ("cl", "cl", "cl"), 8),
    (1, (1, 1), 3, (2, 5), ("cl", "nchw"), 1),  # one source pixel: every output pixel copies it
    (3, (4, 1), 1, (130, 3), ("nchw", "slice"), 8),
    (2, (6, 6), 0, (3, 4, 5), ("slice", "cl", "nchw"), 16),
    (4, (32, 40), 16, (128, 3, 128), ("cl", "cl", "cl"), 8),  # the predictor's shared input, smaller
]


@pytest.mark.parametrize("B,size,p,channels,layouts,multiple", CASES)
def test_cat_channels_with_pads_matches_the_gather_reference(B, size, p, channels, layouts, multiple):
    tensors, pads = _case(B, size, p, channels, layouts, torch.float64, "cpu")
    width = -(-sum(channels) // multiple) * multiple
    for t in tensors:
        t.requires_grad_(True)
    out = cat_channels(tensors, multiple, pads)
    torch.testing.assert_close(out, reference(tensors, pads, width), rtol=0, atol=0)
    g = torch.randn(out.shape, dtype=torch.float64)
    got = torch.autograd.grad(out, tensors, g)
    want = torch.autograd.grad(reference(tensors, pads, width), tensors, g)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def _biases(channels, which, dtype, device, seed=5):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(C, generator=g, dtype=torch.float64).to(device=device, dtype=dtype) if k in which else None
            for k, C in enumerate(channels)]


@pytest.mark.parametrize("B,size,p,channels,layouts,multiple", CASES)
def test_cat_channels_with_biases_matches_the_gather_reference(B, size, p, channels, layouts, multiple):
    """A bias given with a source is added to each of its copied values; its gradient is the channel's sum of
    the output's gradient over every pixel that copied the source (padding included)."""
    tensors, pads = _case(B, size, p, channels, layouts, torch.float64, "cpu")
    biases = _biases(channels, {0, len(channels) - 1}, torch.float64, "cpu")
    width = -(-sum(channels) // multiple) * multiple
    wrt = [*tensors, *(b for b in biases if b is not None)]
    for t in wrt:
        t.requires_grad_(True)
    out = cat_channels(tensors, multiple, pads, biases)
    want = reference(tensors, pads, width, biases)
    torch.testing.assert_close(out, want, rtol=0, atol=1e-15)
    g = torch.randn(out.shape, dtype=torch.float64)
    for a, b in zip(torch.autograd.grad(out, wrt, g), torch.autograd.grad(want, wrt, g)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_cat_channels_rejects_a_bias_of_the_wrong_size():
    a, b = torch.zeros(2, 3, 8, 8), torch.zeros(2, 4, 8, 8)
    for biases in ([torch.zeros(3)], [torch.zeros(4), None], [None, torch.zeros(4, 1)]):
        with pytest.raises(ValueError, match="a bias per tensor"):
            cat_channels([a, b], 1, [0, 0], biases)


@kernel_test
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_concat_kernels_add_the_biases_and_sum_their_gradients(dtype):
    """The Triton kernels themselves (on CUDA, or Triton's interpreter on the CPU): biases on the first and last
    of three sources, one of them edge-replicated, values against the float64 reference and each source's bias
    gradient (the programs' channel sums, added up) against the sum of the output's gradient over that source's
    channels; a source without a bias gives none."""
    from sgmodel.kernels import concat as concat_kernels

    tensors, pads = _case(2, (6, 37), 2, (3, 1, 70), ("cl", "nchw", "slice"), dtype, KERNEL_DEVICE)
    biases = _biases((3, 1, 70), {0, 2}, torch.float32, KERNEL_DEVICE)
    out = concat_kernels.forward(tensors, pads, 80, biases)
    want = reference(tensors, pads, 80, biases)
    tol = 0 if dtype == torch.float64 else 1e-6
    torch.testing.assert_close(out.double(), want, rtol=tol, atol=tol)
    g = torch.randn(out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2)).to(KERNEL_DEVICE, dtype)
    lo = 0
    for t, p, b in zip(tensors, pads, biases):
        dx, db = concat_kernels.backward(g, lo, t.shape[1], p, t.shape[2], t.shape[3], dtype,
                                         None if b is None else torch.float32)
        assert dx.shape == t.shape and (db is None) == (b is None)
        if b is not None:
            assert db.dtype == torch.float32
            torch.testing.assert_close(db.double(), g[:, lo:lo + t.shape[1]].double().sum((0, 2, 3)), rtol=1e-5,
                                       atol=1e-5)
        lo += t.shape[1]


def test_cat_channels_rejects_sizes_that_do_not_meet():
    a, b = torch.zeros(2, 3, 8, 8), torch.zeros(2, 4, 4, 4)
    assert cat_channels([a, b], 1, [0, 2]).shape == (2, 7, 8, 8)
    for tensors, pads in (([a, b], [0, 1]), ([a, b], [0]), ([a, b], [0, -2]), ([a, b.double()], [0, 2]),
                          ([a, torch.zeros(1, 4, 4, 4)], [0, 2])):
        with pytest.raises(ValueError, match="cat_channels"):
            cat_channels(tensors, 1, pads)


@needs_cuda
@pytest.mark.parametrize("B,size,p,channels,layouts,multiple", CASES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("need", ["all", "last", "none"])
def test_concat_kernels_match_float64_on_cuda(B, size, p, channels, layouts, multiple, dtype, need):
    """The Triton concatenation: the values exactly (a copy), channels-last; each gradient that is wanted
    within the rounding of the source's dtype of the float64 sum (up to (p+1)^2 terms at a corner), and no
    other computed."""
    tensors, pads = _case(B, size, p, channels, layouts, dtype, "cuda", seed=B + p)
    wanted = [need == "all" or (need == "last" and k == len(tensors) - 1) for k in range(len(tensors))]
    for t, w in zip(tensors, wanted):
        t.requires_grad_(w)
    width = -(-sum(channels) // multiple) * multiple
    out = cat_channels(tensors, multiple, pads)
    assert out.dtype == dtype and out.is_contiguous(memory_format=CL)
    want = reference(tensors, pads, width)
    torch.testing.assert_close(out.double(), want, rtol=0, atol=0)
    if not any(wanted):
        assert not out.requires_grad
        return
    g = torch.randn(out.shape, dtype=torch.float64, device="cuda",
                    generator=torch.Generator("cuda").manual_seed(1)).to(dtype)
    wrt = [t for t, w in zip(tensors, wanted) if w]
    got = torch.autograd.grad(out, wrt, g)
    ref_in = [t.detach().double().requires_grad_(w) for t, w in zip(tensors, wanted)]
    ref = torch.autograd.grad(reference(ref_in, pads, width), [t for t in ref_in if t.requires_grad], g.double())
    eps = torch.finfo(dtype).eps
    for a, b, t in zip(got, ref, wrt):
        assert a.dtype == dtype and a.shape == t.shape and a.is_contiguous(memory_format=CL)
        # one rounding of the float32 sum to the dtype, plus float32's own on up to (p+1)^2 terms
        torch.testing.assert_close(a.double(), b, rtol=eps, atol=eps * 1e-3 + 1e-6 * (p + 1) ** 2)


@needs_cuda
@pytest.mark.parametrize("B,size,p,channels,layouts,multiple", CASES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_concat_kernels_with_biases_match_float64_on_cuda(B, size, p, channels, layouts, multiple, dtype):
    """Biases (float32, as a convolution's parameters are) on the first and last sources: the values within one
    rounding to the dtype of the float64 sums; the sources' and the biases' gradients against float64."""
    tensors, pads = _case(B, size, p, channels, layouts, dtype, "cuda", seed=B + p)
    biases = _biases(channels, {0, len(channels) - 1}, torch.float32, "cuda")
    wrt = [*tensors, *(b for b in biases if b is not None)]
    for t in wrt:
        t.requires_grad_(True)
    width = -(-sum(channels) // multiple) * multiple
    out = cat_channels(tensors, multiple, pads, biases)
    want = reference(tensors, pads, width, biases)
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(out.double(), want, rtol=eps, atol=eps * 1e-3)
    g = torch.randn(out.shape, dtype=torch.float64, device="cuda",
                    generator=torch.Generator("cuda").manual_seed(1)).to(dtype)
    ref_in = [t.detach().double().requires_grad_(True) for t in wrt]
    n = len(tensors)
    ref_biases = iter(ref_in[n:])
    ref = reference(ref_in[:n], pads, width, [None if b is None else next(ref_biases) for b in biases])
    got, ref = torch.autograd.grad(out, wrt, g), torch.autograd.grad(ref, ref_in, g.double())
    for a, b in zip(got[:n], ref[:n]):  # the sources': as without biases
        torch.testing.assert_close(a.double(), b, rtol=eps, atol=eps * 1e-3 + 1e-6 * (p + 1) ** 2)
    scale = g.double().abs().sum((0, 2, 3)).max()  # the biases': float32 sums of up to B Hd Wd terms
    for a, b in zip(got[n:], ref[n:]):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a.double(), b, rtol=0, atol=1e-5 * float(scale))


@needs_cuda
@pytest.mark.parametrize("rgbd,descriptor", [(True, True), (True, False), (False, True)])
def test_predictor_with_the_descriptor_padded_inside_matches_the_cpu_on_cuda(rgbd, descriptor, monkeypatch):
    """The predictor on CUDA (channels-last, channels padded to 8, the Triton concatenations extending phi
    by ``phi_padding`` and adding phi's bias and the regressor's) against the same weights on the CPU given phi
    already padded (by the reference gather) with its bias added, both in float64: outputs and every gradient
    (phi's, its bias's, the weights')."""
    monkeypatch.setattr(predictor_module, "compute_dtype", lambda device: torch.float64)
    torch.manual_seed(0)
    params = PredictorParams(channels=16, groups=4)
    C, P = (12 if descriptor else 0), 3
    net = GaussianPredictor(params, C, rgbd).double()
    with torch.no_grad():
        for t in net.parameters():
            t.normal_(std=0.2)
    rgb, z = torch.rand(2, 3, 14, 18, dtype=torch.float64), 1 + torch.rand(2, 1, 14, 18, dtype=torch.float64)
    phi = torch.randn(2, C, 8, 12, dtype=torch.float64) if descriptor else None
    bias = torch.randn(C, dtype=torch.float64) if descriptor else None

    def run(device, pad_inside):
        model = copy.deepcopy(net).to(device)
        p = None if phi is None else phi.to(device).requires_grad_(True)
        b = None if bias is None else bias.to(device).requires_grad_(True)
        given = p if p is None or pad_inside else reference([p], [P], C, [b])
        outs = model(rgb.to(device), z.to(device), given, phi_padding=P if pad_inside else 0,
                     phi_bias=b if pad_inside else None)
        weights = torch.linspace(0, 1, 40, dtype=torch.float64, device=device)
        loss = sum((o * weights[:o.shape[1], None, None]).sum() for o in outs)
        wrt = list(model.parameters()) + ([p, b] if p is not None else [])
        return [o.cpu() for o in outs] + [g.cpu() for g in torch.autograd.grad(loss, wrt)]

    for a, b in zip(run("cuda", pad_inside=True), run("cpu", pad_inside=False)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)



def test_decoder_casts_its_resized_inputs_to_the_convolutions_dtype(monkeypatch):
    """CUDA's autocast resizes in float32 whatever the input's dtype; the decoder casts the resized RGB and
    depth to its convolutions' dtype before they meet the features (``cat_channels`` takes one dtype, as
    its CUDA kernels do). Here the resize is made to answer in float32 while the layers run in float64 on
    the CPU: the layers run, and give the float64 result to float32's rounding."""
    model, left, z, features, K = layers_case()
    for module in (decoder_module, predictor_module):
        monkeypatch.setattr(module, "compute_dtype", lambda device: torch.float64)
    want = model.layers(left, z, features, K)[:3]
    interpolate = torch.nn.functional.interpolate
    monkeypatch.setattr(torch.nn.functional, "interpolate", lambda *a, **k: interpolate(*a, **k).float())
    got = model.layers(left, z, features, K)[:3]
    for a, b in zip(got, want):
        assert a.dtype == torch.float64
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
