"""sgmodel.kernels.soft_argmin: PSMNet's full-resolution soft-argmin without the volume, against the
float64 volume computation (trilinear upsampling, softmax, expectation) it replaces; degenerate sizes
and extreme costs. And the single-output-channel classifier convolution's CUDA path."""

import pytest
import torch

from sgmodel.encoders.psmnet import ScoreConv3d
from sgmodel.kernels.soft_argmin import soft_argmin, soft_argmin_reference


@pytest.mark.parametrize("shape,levels,height,width", [
    ((2, 48, 8, 12), 192, 32, 48),  # PSMNet's layout: 1/4 scale, 4 disparities per coarse level
    ((1, 48, 5, 7), 192, 17, 25),  # sizes that are not multiples of the scale
    ((1, 3, 1, 1), 12, 4, 4),  # one coarse pixel
    ((1, 4, 3, 3), 16, 1, 1),  # one output pixel (scale 0)
    ((1, 1, 2, 2), 1, 3, 3),  # one disparity level
    ((1, 2, 4, 4), 5, 7, 2),
])
def test_soft_argmin_matches_the_float64_volume(shape, levels, height, width):
    torch.manual_seed(0)
    cost = torch.randn(*shape) * 5
    ours = soft_argmin(cost, levels, height, width)
    ref = soft_argmin_reference(cost.double(), levels, height, width)
    assert ours.shape == (shape[0], 1, height, width) and ours.dtype == torch.float32
    # float32 interpolation weights differ from float64's by ~1e-7 relative; at sharp cost peaks that
    # moves the expectation by up to ~1e-3 px (the float32 PyTorch computation is off by as much)
    torch.testing.assert_close(ours.double(), ref, rtol=0, atol=2e-3)
    assert ours.min() >= 0 and ours.max() <= levels - 1


def test_soft_argmin_extreme_costs_stay_finite():
    cost = torch.zeros(1, 48, 4, 4)
    cost[0, 10] = 1e30  # one overwhelming level: the argmax, exactly where the interpolation peaks
    assert torch.allclose(soft_argmin(cost, 192, 16, 16), soft_argmin_reference(cost.double(), 192, 16, 16).float())
    flat = soft_argmin(torch.full((1, 48, 4, 4), -1e30), 192, 16, 16)  # all equal, hugely negative
    torch.testing.assert_close(flat, torch.full_like(flat, 95.5))  # uniform: the mean of 0..191
    wild = soft_argmin(torch.randn(1, 48, 4, 4) * 1e6, 192, 16, 16)
    assert torch.isfinite(wild).all()
    half = soft_argmin(torch.randn(1, 48, 4, 4).half(), 192, 16, 16)  # any float dtype is read as float32
    assert half.dtype == torch.float32 and torch.isfinite(half).all()


def test_soft_argmin_refuses_bad_shapes():
    with pytest.raises(ValueError, match="cost"):
        soft_argmin(torch.zeros(48, 4, 4), 192, 16, 16)
    with pytest.raises(ValueError, match="cost"):
        soft_argmin(torch.zeros(1, 48, 4, 4), 0, 16, 16)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (the padded path runs on CUDA only)")
def test_score_conv_cuda_path_equals_plain_convolution():
    torch.manual_seed(0)
    conv = ScoreConv3d(8).cuda()
    plain = torch.nn.Conv3d(8, 1, 3, 1, 1, bias=False).cuda()
    plain.load_state_dict(conv.state_dict())
    x = torch.randn(2, 8, 6, 10, 12, device="cuda")
    torch.testing.assert_close(conv(x), plain(x), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(soft_argmin(x[:, :6, 0], 24, 20, 24),
                               soft_argmin_reference(x[:, :6, 0].double(), 24, 20, 24).float(), rtol=0, atol=2e-3)
