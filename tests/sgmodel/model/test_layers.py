"""sgmodel.model.layers against the PyTorch operations they replace (float64, values and gradients), including
degenerate sizes; the fused predictor branches against plain PyTorch branches; the CUDA layout (channels-last
activations, channels padded to multiples of 8) against NCHW on the CPU; and, on CUDA with Triton, the
fused GroupNorm + GELU kernels against PyTorch in float64."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from sgmodel.config import PredictorParams
from sgmodel.kernels import channels_last_kernels_run
from sgmodel.model import decoder, layers, predictor
from sgmodel.model.layers import (GroupNorm, ReplicateConv2d, cat_channels, compute_dtype, group_norm_gelu,
                                  group_norm_gelu_parts, replicate_conv3x3, replicate_pad, upsample_bilinear)
from sgmodel.model.predictor import GaussianPredictor, fused_branches
from tests.support.kernels import KERNEL_DEVICE, kernel_test, skip_if_too_large_to_interpret
from tests.support.model_helpers import layers_case

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
    """Input channels beyond the weight's (``cat_channels``: the bias channel of ones, then zeros) and outputs
    computed padded to ``multiple``: the same values and gradients as PyTorch's replicate-padded
    convolution of the real channels (float64), with the bias carried by the ones channel, also when only
    the bias needs a gradient."""
    torch.manual_seed(2)
    x = torch.randn(2, cin, *size, dtype=torch.float64)
    w = torch.randn(cout, cin, 3, 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(cout, dtype=torch.float64, requires_grad=True)
    xr = x.clone().requires_grad_(True)
    ref = F.conv2d(F.pad(xr, (1, 1, 1, 1), mode="replicate"), w, b)
    xp = cat_channels([x.contiguous(memory_format=layout)], cin + extra)
    assert xp.shape[1] == cin + extra
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
    (gb,) = torch.autograd.grad(replicate_conv3x3(xp.detach(), w.detach(), b, multiple), [b], g)
    torch.testing.assert_close(gb, want[2], rtol=1e-11, atol=1e-11)
    with pytest.raises(ValueError, match="channels"):
        replicate_conv3x3(x[:, :cin - 1], w, b)


@pytest.mark.parametrize("layout", [torch.contiguous_format, CL])
def test_cat_channels_pads_with_ones_then_zeros_in_the_first_layout(layout):
    a = torch.randn(2, 3, 4, 5).contiguous(memory_format=layout)
    b = torch.randn(2, 6, 4, 5)
    out = cat_channels([a, b], 8)
    assert out.shape == (2, 16, 4, 5)
    assert torch.equal(out[:, :3], a) and torch.equal(out[:, 3:9], b)
    assert (out[:, 9] == 1).all() and not out[:, 10:].any()
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
    assert not channels_last_kernels_run(x)
    torch.testing.assert_close(group_norm_gelu(x, 3, w, b, 1e-5), F.gelu(F.group_norm(x, 3, w, b, 1e-5)),
                               rtol=0, atol=0)
    torch.testing.assert_close(group_norm_gelu(x, 3, w, b, 1e-5, gelu=False), F.group_norm(x, 3, w, b, 1e-5),
                               rtol=0, atol=0)


@pytest.mark.parametrize("inputs,outputs", [(8, 8), (layers.CUDA_INPUT_MULTIPLE, layers.CUDA_OUTPUT_MULTIPLE)])
def test_cuda_layout_computes_the_same_model_on_the_cpu(monkeypatch, inputs, outputs):
    """The decoder and predictor with CUDA's layout (channels-last activations, concatenated inputs and
    convolution outputs padded to multiples of their own) give the NCHW results and gradients, in float64
    on the CPU."""
    model, left, z, features, K = layers_case()
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
    monkeypatch.setattr(layers, "output_multiple", lambda x: outputs)
    monkeypatch.setattr(predictor, "output_multiple", lambda x: outputs)
    monkeypatch.setattr(predictor, "input_multiple", lambda x: inputs)
    padded = run()
    for a, b in zip(nchw[0] + list(nchw[1]), padded[0] + list(padded[1])):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@kernel_test
@pytest.mark.parametrize("shape,groups,gelu,dtype,parts", [
    ((2, 384, 37, 41), 24, True, torch.float32, 1), ((3, 128, 16, 16), 8, False, torch.float32, 1),
    ((2, 12, 5, 7), 3, True, torch.float32, 1), ((1, 24, 1, 1), 2, True, torch.float32, 1),
    ((2, 10, 300, 7), 5, True, torch.float32, 1), ((4, 384, 64, 64), 24, True, torch.bfloat16, 1),
    ((2, 384, 37, 41), 24, True, torch.float32, 3), ((2, 12, 5, 7), 4, False, torch.float32, 2),
    ((4, 384, 64, 64), 24, True, torch.bfloat16, 3)])
def test_fused_group_norm_gelu_matches_pytorch_float64(shape, groups, gelu, dtype, parts):
    """Values and the three gradients of the Triton kernels against float64 PyTorch on the same inputs;
    channel blocks of 16, 4, 12 (not a power of two) and 2, one-pixel images, a mean far from zero; and
    the output in parts (the predictor's branches), each its own channels-last tensor, with one cotangent
    per part, against the float64 whole split."""
    skip_if_too_large_to_interpret(shape)
    torch.manual_seed(0)
    C = shape[1]
    x = (torch.randn(shape, device=KERNEL_DEVICE) * 3 + 20).to(dtype).contiguous(memory_format=CL).requires_grad_(True)
    w = torch.randn(C, device=KERNEL_DEVICE, requires_grad=True)
    b = torch.randn(C, device=KERNEL_DEVICE, requires_grad=True)
    ys = group_norm_gelu_parts(x, groups, w, b, 1e-5, gelu, parts) if parts > 1 else [
        group_norm_gelu(x, groups, w, b, 1e-5, gelu)]
    assert all(y.dtype == dtype and y.shape == (shape[0], C // parts, *shape[2:]) and y.is_contiguous(memory_format=CL)
               for y in ys)
    xd, wd, bd = (t.detach().double().requires_grad_(True) for t in (x, w, b))
    ref = F.group_norm(xd, groups, wd, bd, 1e-5)
    refs = (F.gelu(ref) if gelu else ref).split(C // parts, dim=1)
    dys = [torch.randn(r.shape, device=KERNEL_DEVICE).to(dtype).contiguous(memory_format=CL) for r in refs]
    got = torch.autograd.grad(ys, [x, w, b], dys)
    want = torch.autograd.grad(refs, [xd, wd, bd], [d.double() for d in dys])
    tol = 1e-5 if dtype == torch.float32 else 1e-2  # relative to the largest magnitude; bf16 rounds y and dx
    for name, u, v in [*(("y", u, v) for u, v in zip(ys, refs)), *zip(("dx", "dgamma", "dbeta"), got, want)]:
        err = ((u.double() - v).abs().max() / v.abs().max()).item()
        assert err < (1e-5 if name in ("dgamma", "dbeta") else tol), (name, err)


def test_group_norm_gelu_in_parts_splits_the_whole_on_the_cpu():
    torch.manual_seed(0)
    x = torch.randn(2, 12, 5, 6, dtype=torch.float64)
    w, b = torch.randn(12, dtype=torch.float64), torch.randn(12, dtype=torch.float64)
    whole = group_norm_gelu(x, 6, w, b, 1e-5)
    parts = group_norm_gelu_parts(x, 6, w, b, 1e-5, True, 3)
    assert [p.shape[1] for p in parts] == [4, 4, 4]
    torch.testing.assert_close(torch.cat(parts, 1), whole, rtol=0, atol=0)


def test_upsample_bilinear_is_interpolate_in_the_consumers_dtype():
    """Off the Triton path: ``F.interpolate`` (align_corners=False), cast to the dtype asked for; sizes that are
    not an exact 2x go this way everywhere."""
    torch.manual_seed(0)
    x = torch.randn(2, 5, 6, 7, dtype=torch.float64)
    for size in ((12, 14), (11, 13), (6, 7)):
        want = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        torch.testing.assert_close(upsample_bilinear(x, size, torch.float64), want, rtol=0, atol=0)
        assert upsample_bilinear(x, size, torch.float32).dtype == torch.float32


@kernel_test
@pytest.mark.parametrize("shape,dtype,out_dtype", [
    ((2, 70, 5, 7), torch.float32, torch.float32), ((1, 8, 1, 1), torch.float32, torch.float32),
    ((3, 128, 16, 9), torch.float32, torch.bfloat16), ((32, 128, 128, 128), torch.float32, torch.bfloat16),
    ((2, 64, 9, 4), torch.bfloat16, torch.bfloat16)])
def test_upsample_bilinear_2x_matches_pytorch_float64(shape, dtype, out_dtype):
    """The Triton 2x kernels (values in the consumer's dtype; the gradient gathered, not scattered) against
    float64 ``F.interpolate`` and its gradient, including one-pixel images and odd sizes; and, written in
    bf16, PyTorch's float32 resize rounded to bf16 bit for bit in all but a few elements."""
    skip_if_too_large_to_interpret(shape)
    torch.manual_seed(0)
    B, C, h, w = shape
    x = torch.randn(shape, device=KERNEL_DEVICE).to(dtype).contiguous(memory_format=CL).requires_grad_(True)
    y = upsample_bilinear(x, (2 * h, 2 * w), out_dtype)
    assert y.dtype == out_dtype and y.is_contiguous(memory_format=CL)
    xd = x.detach().double().requires_grad_(True)
    ref = F.interpolate(xd, size=(2 * h, 2 * w), mode="bilinear", align_corners=False)
    g = torch.randn(ref.shape, device=KERNEL_DEVICE).to(out_dtype).contiguous(memory_format=CL)
    (gx,) = torch.autograd.grad(y, x, g)
    (gr,) = torch.autograd.grad(ref, xd, g.double())
    assert gx.dtype == dtype
    tol = 1e-6 if out_dtype == torch.float32 else 1e-2
    assert ((y.double() - ref).abs().max() / ref.abs().max()).item() < tol
    assert ((gx.double() - gr).abs().max() / gr.abs().max()).item() < (1e-6 if dtype == torch.float32 else 1e-2)
    # bit for bit on a GPU (Triton's interpreter rounds to bf16 its own way); float32 results may differ in the
    # last ulp (FMA)
    if dtype == torch.float32 and out_dtype == torch.bfloat16 and KERNEL_DEVICE == "cuda":
        torch_fp32 = F.interpolate(x.detach(), size=(2 * h, 2 * w), mode="bilinear", align_corners=False)
        assert (y != torch_fp32.to(out_dtype)).float().mean().item() < 1e-3


def test_conv_gelu_is_the_convolution_then_gelu_off_cuda():
    """Off the Triton path ``conv_gelu`` is ``nn.Conv2d`` (bias included) then GELU: float64 values and every
    gradient; and the decoder's modules keep their state_dict keys."""
    torch.manual_seed(0)
    conv = nn.Conv2d(6, 5, 3, padding=1).double()
    x = torch.randn(2, 6, 7, 4, dtype=torch.float64, requires_grad=True)
    got = layers.conv_gelu(conv, x)
    want = F.gelu(conv(x))
    torch.testing.assert_close(got, want, rtol=1e-14, atol=1e-14)
    g = torch.randn_like(want)
    wrt = [x, conv.weight, conv.bias]
    for u, v in zip(torch.autograd.grad(got, wrt, g), torch.autograd.grad(want, wrt, g)):
        torch.testing.assert_close(u, v, rtol=1e-13, atol=1e-13)
    keys = set(decoder.ResidualConvUnit(4).state_dict())
    assert keys == {"conv1.weight", "conv1.bias", "conv2.weight", "conv2.bias"}


@kernel_test
@pytest.mark.parametrize("shape,dtype", [((32, 128, 64, 64), torch.bfloat16), ((2, 128, 33, 17), torch.float32),
                                         ((3, 40, 5, 7), torch.bfloat16), ((1, 8, 1, 1), torch.float32)])
def test_bias_gelu_matches_float64(shape, dtype):
    """The Triton GELU(x + bias) against float64 PyTorch on the same (rounded) inputs: y and dx within x's dtype's
    rounding, the bias gradient (summed in float32 over every pixel, in the backward's own pass) within
    float32's; many pixels, a channel count that is not a power of two, pixels that leave a tile part empty,
    one pixel; values far into both tails of the GELU."""
    skip_if_too_large_to_interpret(shape)
    torch.manual_seed(0)
    C = shape[1]
    x = (torch.randn(shape, device=KERNEL_DEVICE) * 4).to(dtype).contiguous(memory_format=CL).requires_grad_(True)
    b = torch.randn(C, device=KERNEL_DEVICE, requires_grad=True)
    y = layers.bias_gelu(x, b)
    assert y.dtype == dtype and y.is_contiguous(memory_format=CL)
    xd, bd = (t.detach().double().requires_grad_(True) for t in (x, b))
    ref = F.gelu(xd + bd.view(-1, 1, 1))
    g = torch.randn(shape, device=KERNEL_DEVICE).to(dtype).contiguous(memory_format=CL)
    gx, gb = torch.autograd.grad(y, [x, b], g)
    rx, rb = torch.autograd.grad(ref, [xd, bd], g.double())
    assert gx.dtype == dtype and gb.dtype == torch.float32
    tol = 1e-5 if dtype == torch.float32 else 2 ** -7  # relative: one bf16 ulp (y and dx are rounded once)
    torch.testing.assert_close(y.double(), ref, rtol=tol, atol=1e-6)
    torch.testing.assert_close(gx.double(), rx, rtol=tol, atol=1e-6)
    scale = rx.abs().sum(dim=(0, 2, 3)).max()  # what the float32 sum adds up
    assert ((gb.double() - rb).abs().max() / scale).item() < 1e-5
