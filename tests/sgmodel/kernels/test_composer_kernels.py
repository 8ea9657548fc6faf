"""The composer's Triton kernels (``sgmodel.kernels.composer``; where they run: tests/support/kernels.py) against
the composer's PyTorch path: in float64 (itself tested against the float64 reference of appendix A in
tests/sgmodel/model/test_composer.py), and in float32 with residuals exactly on the scale caps."""

from __future__ import annotations

import pytest
import torch

from sgmodel.model import composer as comp
from sgmodel.model.layers import CUDA_OUTPUT_MULTIPLE, round_up
from tests.support.composer_inputs import make_inputs
from tests.support.kernels import KERNEL_DEVICE, kernel_test

#: the final convs' output channels as the model computes them on CUDA (37 rounded up)
WIDE = round_up(37, CUDA_OUTPUT_MULTIPLE)


def _fused_case(dtype: torch.dtype, H: int = 40, W: int = 56):
    """Inputs as the model gives them on CUDA, on ``KERNEL_DEVICE``: the branches as 37-channel views of
    ``WIDE``-channel channels-last conv outputs in ``dtype`` (leaves: the wide tensors), extreme residuals, zero
    quaternion vectors, clipped scales."""
    g = torch.Generator().manual_seed(3)
    B = 2
    _, _, dz, z, rgb, K, baseline = make_inputs(B=B, H=H, W=W, dtype=torch.float32)
    wide = [3.0 * torch.randn(B, WIDE, H, W, generator=g) for _ in range(2)]
    for w in wide:
        w[:, :, 0, :4] *= 3e3  # huge residuals: saturated sigmoids, clipped scales
        w[:, 6:10, 1, 0] = torch.tensor([-10.0, 0.0, 0.0, 0.0])  # (1,0,0,0) + 0.1 dq = 0: the identity
        w[:, 3:6, 1, 1] = -200.0  # below S_MIN after phi
    z = z.clone()
    z[:, :, 2, :3] = 1e-6
    wide = [w.to(dtype).contiguous(memory_format=torch.channels_last).to(KERNEL_DEVICE).requires_grad_() for w in wide]
    rest = [t.to(KERNEL_DEVICE) for t in (dz, z, rgb, K, baseline)]
    rest[0].requires_grad_()
    return wide, rest


def _cotangents(out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    g = torch.Generator(device=next(iter(out.values())).device).manual_seed(4)
    return {k: torch.randn(v.shape, generator=g, device=v.device, dtype=torch.float32) for k, v in out.items()}


@kernel_test
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("back_layer", [True, False])
def test_fused_kernels_match_the_float64_composer(dtype: torch.dtype, back_layer: bool) -> None:
    """The fused kernels' attributes and gradients (of the branches, in their dtype, and of dz) against the PyTorch
    composer in float64 on the same values."""
    wide, (dz, z, rgb, K, baseline) = _fused_case(dtype)
    branches = [w[:, :37] for w in wide]
    assert comp._fused_runs(branches[0], z, rgb, True, "none")
    out = comp.compose(branches[0], branches[1], dz, z, rgb, K, baseline, back_layer=back_layer)
    leaves64 = [b.detach().double().requires_grad_() for b in branches] + [dz.detach().double().requires_grad_()]
    ref = comp.compose(leaves64[0], leaves64[1], leaves64[2], z.double(), rgb.double(), K.double(),
                       baseline.double(), back_layer=back_layer)
    cot = _cotangents(out)
    for k in ref:
        assert out[k].dtype == torch.float32 and out[k].shape == ref[k].shape, k
        torch.testing.assert_close(out[k].double(), ref[k], rtol=2e-6, atol=2e-6, msg=k)
    sum((out[k] * cot[k]).sum() for k in out).backward()
    sum((ref[k] * cot[k].double()).sum() for k in ref).backward()
    layers = 2 if back_layer else 1
    # float32: a saturated sigmoid's slope a (1 - a) has 1 - a below 1e-3, where an ulp of a (the kernels' exp and
    # PyTorch's differ by one or two) moves it by 1e-4 relative: up to 3.3e-7 apart on the H100 in 9 of 165,760
    tol = dict(rtol=1e-2, atol=1e-6) if dtype == torch.bfloat16 else dict(rtol=1e-4, atol=1e-6)
    for i in range(layers):
        assert wide[i].grad.dtype == dtype
        torch.testing.assert_close(wide[i].grad[:, :37].double(), leaves64[i].grad.to(dtype).double(), **tol)
        assert not wide[i].grad[:, 37:].any()
    if back_layer:
        torch.testing.assert_close(dz.grad.double(), leaves64[2].grad, rtol=1e-4, atol=1e-6)
    else:
        assert wide[1].grad is None and dz.grad is None


@kernel_test
def test_fused_kernels_match_the_pytorch_composer_in_float32() -> None:
    """Against the PyTorch path in float32 on the same device (z~ wanting a gradient sends compose there), with residuals
    exactly on the scale caps: ``minimum`` halves the gradient on a tie, and so do the kernels."""
    wide, (dz, z, rgb, K, baseline) = _fused_case(torch.float32)
    with torch.no_grad():
        wide[0][:, 3:6] = comp.scale_cap(comp.S_CAP_FRONT_EDGE)  # ties where the band is, below the cap elsewhere
        wide[1][:, 3, :, :5] = comp.scale_cap(comp.S_CAP_BACK)
    band = comp.edge_band(z, K, baseline)
    assert band.any() and not band.all()
    out = comp.compose(wide[0][:, :37], wide[1][:, :37], dz, z, rgb, K, baseline)
    eager_leaves = [w.detach().clone().requires_grad_() for w in wide] + [dz.detach().clone().requires_grad_()]
    z_grad = z.clone().requires_grad_()
    assert not comp._fused_runs(eager_leaves[0], z_grad, rgb, True, "none")
    ref = comp.compose(eager_leaves[0][:, :37], eager_leaves[1][:, :37], eager_leaves[2], z_grad, rgb, K, baseline)
    cot = _cotangents(out)
    for k in ref:
        torch.testing.assert_close(out[k], ref[k], rtol=2e-6, atol=2e-6, msg=k)
    sum((out[k] * cot[k]).sum() for k in out).backward()
    sum((ref[k] * cot[k]).sum() for k in ref).backward()
    for mine, theirs in zip([*wide, dz], eager_leaves):
        torch.testing.assert_close(mine.grad, theirs.grad, rtol=1e-4, atol=1e-6)  # (the slopes above)
