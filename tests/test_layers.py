"""sgmodel.layers against the PyTorch operations they replace (float64, values and gradients), including
degenerate sizes, and the fused predictor branches against three separate branches."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from sgmodel.config import PredictorParams
from sgmodel.layers import GroupNorm, ReplicateConv2d, compute_dtype, replicate_conv3x3, replicate_pad
from sgmodel.predictor import GaussianPredictor, fused_branches


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


def test_fused_branches_equal_separate_branches():
    torch.manual_seed(0)
    p = GaussianPredictor(PredictorParams(channels=16, groups=4), 8, True, True).double()
    with torch.no_grad():
        for t in p.parameters():
            t.normal_(std=0.3)
    x = torch.randn(2, 16 + 3 + 8, 9, 11, dtype=torch.float64, requires_grad=True)
    fused = fused_branches([p.front, p.back, p.dz], x)
    separate = [p.front(x), p.back(x), p.dz(x)]
    for a, b in zip(fused, separate):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    params = [x, *p.parameters()]
    ga = torch.autograd.grad(sum(t.square().sum() for t in fused), params, allow_unused=True)
    gb = torch.autograd.grad(sum(t.square().sum() for t in separate), params, allow_unused=True)
    for a, b in zip(ga, gb):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
