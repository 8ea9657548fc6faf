"""sgmodel.layers against the PyTorch operations they replace (float64, values and gradients), including
degenerate sizes; the fused predictor branches against plain PyTorch branches; the CUDA layout (channels-last
activations, channels padded to multiples of 8) against NCHW on the CPU; and, on CUDA with Triton, the
fused GroupNorm + GELU kernels against PyTorch in float64."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from sgmodel import decoder, layers, predictor
from sgmodel.config import ModelParams, PredictorParams
from sgmodel.layers import (GroupNorm, ReplicateConv2d, cat_channels, compute_dtype, fused_group_norm_available,
                            group_norm_gelu, replicate_conv3x3, replicate_pad)
from sgmodel.model import StereoGaussians
from sgmodel.predictor import GaussianPredictor, fused_branches
from tests.model_helpers import StandInEncoder

CL = torch.channels_last


@pytest.mark.parametrize("shape,p", [((2, 3, 7, 9), 1), ((1, 2, 5, 4), 3), ((1, 1, 1, 1), 2), ((2, 1, 1, 6), 1),
                                     ((1, 2, 3, 2), 16), ((3, 4, 5), 2)])
def test_replicate_pad_matches_torch(shape, p):
    x = torch.randn(*shape, dtype=torch.float64, requires_grad=True)
    ours = replicate_pad(x, p)
    ref_in = x.detach().clone().requires_grad_(True)
    ref = F.pad(ref_in, (p, p, p, p), mode="replicate")
    assert torch.equal(ours, ref)
    g = torch.randn_like(ours)
    (gx,) = torch.autograd.grad(ours, x, g)
    (gr,) = torch.autograd.grad(ref, ref_in, g)
    torch.testing.assert_close(gx, gr, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(lambda t: replicate_pad(t, p), (x,))


@pytest.mark.parametrize("shape,p", [((2, 3, 7, 9), 1), ((1, 5, 4, 6), 3), ((2, 8, 1, 1), 2)])
def test_replicate_pad_keeps_channels_last(shape, p):
    x = torch.randn(*shape, dtype=torch.float64).contiguous(memory_format=CL).requires_grad_(True)
    ours = replicate_pad(x, p)
    assert ours.is_contiguous(memory_format=CL) or shape[-2:] == (1, 1)  # a 1x1 image is both layouts
    ref = F.pad(x.detach().contiguous(), (p, p, p, p), mode="replicate")
    assert torch.equal(ours, ref)
    assert torch.autograd.gradcheck(lambda t: replicate_pad(t, p), (x,))


def test_replicate_pad_zero_and_negative():
    x = torch.randn(1, 1, 3, 3)
    assert replicate_pad(x, 0) is x
    with pytest.raises(ValueError, match="padding"):
        replicate_pad(x, -1)


@pytest.mark.parametrize("size", [(6, 7), (6, 1), (1, 5), (1, 1), (2, 2), (3, 40)])
def test_replicate_conv_matches_torch_conv(size):
    torch.manual_seed(0)
    ours = ReplicateConv2d(5, 4).double()
    ref = nn.Conv2d(5, 4, 3, padding=1, padding_mode="replicate").double()
    ref.load_state_dict(ours.state_dict())  # same keys and shapes
    x = torch.randn(2, 5, *size, dtype=torch.float64, requires_grad=True)
    a, b = ours(x), ref(x)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    ga = torch.autograd.grad(a.square().sum(), [x, ours.weight, ours.bias])
    gb = torch.autograd.grad(b.square().sum(), [x, ref.weight, ref.bias])
    for u, v in zip(ga, gb):
        torch.testing.assert_close(u, v, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("size", [(4, 5), (1, 3), (2, 1)])
def test_replicate_conv_backward_gradcheck_and_partial_needs(size):
    """The hand-written backward (ring gradients added in place) by finite differences, and with only
    some inputs needing a gradient (frozen input, frozen weights, no bias)."""
    torch.manual_seed(1)
    x = torch.randn(2, 3, *size, dtype=torch.float64, requires_grad=True)
    w = torch.randn(4, 3, 3, 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(replicate_conv3x3, (x, w, b))
    assert torch.autograd.gradcheck(replicate_conv3x3, (x, w, None))
    ref = F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), w, b)
    g = torch.randn_like(ref)
    gx_ref, gw_ref = torch.autograd.grad(ref, [x, w], g)
    (gw,) = torch.autograd.grad(replicate_conv3x3(x.detach(), w, b), w, g)
    torch.testing.assert_close(gw, gw_ref, rtol=1e-12, atol=1e-12)
    (gx,) = torch.autograd.grad(replicate_conv3x3(x, w.detach(), None) + b.detach()[:, None, None], x, g)
    torch.testing.assert_close(gx, gx_ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("cin,extra,cout,multiple,size,layout", [
    (5, 3, 37, 8, (6, 7), CL), (5, 0, 4, 8, (1, 3), CL), (3, 5, 9, 4, (4, 1), torch.contiguous_format),
    (4, 4, 8, 8, (3, 3), CL), (2, 6, 1, 8, (2, 2), torch.contiguous_format)])
def test_replicate_conv_with_padded_channels_matches_torch(cin, extra, cout, multiple, size, layout):
    """Zero input channels beyond the weight's and outputs computed padded to ``multiple``: the same values
    and gradients as PyTorch's replicate-padded convolution of the real channels (float64)."""
    torch.manual_seed(2)
    x = torch.randn(2, cin, *size, dtype=torch.float64)
    w = torch.randn(cout, cin, 3, 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(cout, dtype=torch.float64, requires_grad=True)
    xr = x.clone().requires_grad_(True)
    ref = F.conv2d(F.pad(xr, (1, 1, 1, 1), mode="replicate"), w, b)
    xp = cat_channels([x.contiguous(memory_format=layout), torch.zeros(2, extra, *size, dtype=torch.float64)])
    xp.requires_grad_(True)
    ours = replicate_conv3x3(xp, w, b, multiple)
    assert ours.shape == ref.shape
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=1e-12)
    g = torch.randn_like(ref)
    got = torch.autograd.grad(ours, [xp, w, b], g)
    want = torch.autograd.grad(ref, [xr, w, b], g)
    torch.testing.assert_close(got[0][:, :cin], want[0], rtol=1e-11, atol=1e-11)
    for u, v in zip(got[1:], want[1:]):
        torch.testing.assert_close(u, v, rtol=1e-11, atol=1e-11)
    with pytest.raises(ValueError, match="channels"):
        replicate_conv3x3(x[:, :cin - 1], w, b)


@pytest.mark.parametrize("layout", [torch.contiguous_format, CL])
def test_cat_channels_pads_with_zeros_in_the_first_layout(layout):
    a = torch.randn(2, 3, 4, 5).contiguous(memory_format=layout)
    b = torch.randn(2, 6, 4, 5)
    out = cat_channels([a, b], 8)
    assert out.shape == (2, 16, 4, 5)
    assert torch.equal(out[:, :3], a) and torch.equal(out[:, 3:9], b) and not out[:, 9:].any()
    assert cat_channels([a, b]).shape[1] == 9 and cat_channels([a, b, a[:, :1]], 5).shape[1] == 10


def test_replicate_conv_under_bf16_autocast_stays_close():
    torch.manual_seed(0)
    ours = ReplicateConv2d(8, 6)
    ref = nn.Conv2d(8, 6, 3, padding=1, padding_mode="replicate")
    ref.load_state_dict(ours.state_dict())
    x = torch.rand(2, 8, 9, 10)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = ours(x)
    assert y.dtype == torch.bfloat16
    torch.testing.assert_close(y.float(), ref(x), rtol=3e-2, atol=3e-2)
    (gw,) = torch.autograd.grad(y.float().square().sum(), ours.weight)
    assert gw.dtype == torch.float32  # the parameter's dtype, through autocast's cast
    (gw_ref,) = torch.autograd.grad(ref(x).square().sum(), ref.weight)
    torch.testing.assert_close(gw, gw_ref, rtol=5e-2, atol=5e-2 * gw_ref.abs().max().item())


def test_group_norm_matches_torch_and_keeps_dtype():
    torch.manual_seed(0)
    ours, ref = GroupNorm(4, 8), nn.GroupNorm(4, 8)
    with torch.no_grad():
        ours.weight.normal_(), ours.bias.normal_()
    ref.load_state_dict(ours.state_dict())
    x = torch.randn(3, 8, 5, 6) * 10 + 3
    torch.testing.assert_close(ours(x), ref(x), rtol=0, atol=0)
    y = ours(x.bfloat16())
    assert y.dtype == torch.bfloat16
    torch.testing.assert_close(y.float(), ref(x.bfloat16().float()), rtol=2e-2, atol=2e-2)
    assert torch.isfinite(ours(torch.zeros(1, 8, 1, 1))).all()  # zero variance stays finite (eps)


def test_compute_dtype():
    assert compute_dtype(torch.device("cpu")) == torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert compute_dtype(torch.device("cpu")) == torch.bfloat16


def plain_branch(branch, x: torch.Tensor) -> torch.Tensor:
    """conv3x3 (replicate) -> GroupNorm -> GELU -> conv3x3 (replicate) in plain PyTorch, from the branch's
    parameters."""
    conv = lambda t, c: F.conv2d(F.pad(t, (1, 1, 1, 1), mode="replicate"), c.weight, c.bias)  # noqa: E731
    n = branch.norm
    return conv(F.gelu(F.group_norm(conv(x, branch.first), n.num_groups, n.weight, n.bias, n.eps)), branch.final)


def test_fused_branches_equal_separate_branches():
    torch.manual_seed(0)
    p = GaussianPredictor(PredictorParams(channels=16, groups=4), 8, True, True).double()
    with torch.no_grad():
        for t in p.parameters():
            t.normal_(std=0.3)
    x = torch.randn(2, 16 + 3 + 8, 9, 11, dtype=torch.float64, requires_grad=True)
    fused = fused_branches([p.front, p.back, p.dz], x)
    separate = [plain_branch(b, x) for b in (p.front, p.back, p.dz)]
    torch.testing.assert_close(p.front(x), separate[0], rtol=1e-12, atol=1e-12)
    for a, b in zip(fused, separate):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    params = [x, *p.parameters()]
    ga = torch.autograd.grad(sum(t.square().sum() for t in fused), params, allow_unused=True)
    gb = torch.autograd.grad(sum(t.square().sum() for t in separate), params, allow_unused=True)
    for a, b in zip(ga, gb):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


def test_group_norm_gelu_is_pytorch_off_cuda():
    """The reference path: F.group_norm then the exact GELU, in the input's dtype, any layout."""
    torch.manual_seed(0)
    x = (torch.randn(2, 12, 5, 6, dtype=torch.float64) * 4 + 1).contiguous(memory_format=CL)
    w, b = torch.randn(12, dtype=torch.float64), torch.randn(12, dtype=torch.float64)
    assert not fused_group_norm_available(x)
    torch.testing.assert_close(group_norm_gelu(x, 3, w, b, 1e-5), F.gelu(F.group_norm(x, 3, w, b, 1e-5)),
                               rtol=0, atol=0)
    torch.testing.assert_close(group_norm_gelu(x, 3, w, b, 1e-5, gelu=False), F.group_norm(x, 3, w, b, 1e-5),
                               rtol=0, atol=0)


def test_cuda_layout_computes_the_same_model_on_the_cpu(monkeypatch):
    """The decoder and predictor with CUDA's layout (channels-last activations, channels padded to 8) give
    the NCHW results and gradients, in float64 on the CPU."""
    torch.manual_seed(0)
    p = ModelParams(resolution=32, padding=4)
    p.decoder.channels = p.predictor.channels = 16
    p.decoder.groups = p.predictor.groups = 4
    model = StereoGaussians(p, StandInEncoder()).double()
    with torch.no_grad():
        for t in model.parameters():
            t.normal_(std=0.2)
    left = torch.rand(2, 3, 32, 32, dtype=torch.float64)
    z = 1 + torch.rand(2, 1, 32, 32, dtype=torch.float64)
    K = torch.tensor([[30.0, 0, 16], [0, 30, 16], [0, 0, 1]], dtype=torch.float64).expand(2, 3, 3)
    features = model.encoder(left, left).features
    for module in (decoder, predictor):  # float64 convolutions (compute_dtype says float32 off autocast)
        monkeypatch.setattr(module, "compute_dtype", lambda device: torch.float64)

    def run():
        out = model.layers(left, z, features, K)[:3]
        grads = torch.autograd.grad(sum((o * torch.linspace(0, 1, o.shape[1], dtype=o.dtype)[:, None, None]).sum()
                                        for o in out), list(model.parameters()))
        return [o.contiguous() for o in out], grads

    nchw = run()
    for module in (layers, decoder, predictor):
        monkeypatch.setattr(module, "activation_format", lambda x: CL)
    monkeypatch.setattr(layers, "channel_multiple", lambda x: 8)
    monkeypatch.setattr(predictor, "channel_multiple", lambda x: 8)
    padded = run()
    for a, b in zip(nchw[0] + list(nchw[1]), padded[0] + list(padded[1])):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (the Triton GroupNorm kernels)")
@pytest.mark.parametrize("shape,groups,gelu,dtype", [
    ((2, 384, 37, 41), 24, True, torch.float32), ((3, 128, 16, 16), 8, False, torch.float32),
    ((2, 12, 5, 7), 3, True, torch.float32), ((1, 24, 1, 1), 2, True, torch.float32),
    ((2, 10, 300, 7), 5, True, torch.float32), ((4, 384, 64, 64), 24, True, torch.bfloat16)])
def test_fused_group_norm_gelu_matches_pytorch_float64_on_cuda(shape, groups, gelu, dtype):
    """Values and the three gradients of the Triton kernels against float64 PyTorch on the same inputs;
    channel blocks of 16, 4, 12 (not a power of two) and 2, one-pixel images, a mean far from zero."""
    if not fused_group_norm_available(torch.zeros(1, 8, 1, 1, device="cuda").contiguous(memory_format=CL)):
        pytest.skip("Triton is not installed")
    torch.manual_seed(0)
    C = shape[1]
    x = (torch.randn(shape, device="cuda") * 3 + 20).to(dtype).contiguous(memory_format=CL).requires_grad_(True)
    w = torch.randn(C, device="cuda", requires_grad=True)
    b = torch.randn(C, device="cuda", requires_grad=True)
    y = group_norm_gelu(x, groups, w, b, 1e-5, gelu)
    assert y.dtype == dtype and y.is_contiguous(memory_format=CL)
    xd, wd, bd = (t.detach().double().requires_grad_(True) for t in (x, w, b))
    ref = F.group_norm(xd, groups, wd, bd, 1e-5)
    ref = F.gelu(ref) if gelu else ref
    dy = torch.randn(shape, device="cuda").to(dtype).contiguous(memory_format=CL)
    got = torch.autograd.grad(y, [x, w, b], dy)
    want = torch.autograd.grad(ref, [xd, wd, bd], dy.double())
    tol = 1e-5 if dtype == torch.float32 else 1e-2  # relative to the largest magnitude; bf16 rounds y and dx
    for name, u, v in zip(("y", "dx", "dgamma", "dbeta"), (y, *got), (ref, *want)):
        err = ((u.double() - v).abs().max() / v.abs().max()).item()
        assert err < (1e-5 if name in ("dgamma", "dbeta") else tol), (name, err)
