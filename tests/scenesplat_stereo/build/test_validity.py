"""Pixels without a valid stereo depth make no Gaussian: geometry.disparity_validity against a float64 rule
written here, composer.gaussian_validity against explicit windows, the model's Prediction.valid (canvas
padding inherits the replicated pixel's validity), both baselines, and predict's count of dropped ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sgmodel.config import ModelParams
from sgmodel.model.baselines import forward_splat
from sgmodel.model.composer import BACK_POOL, gaussian_validity
from sgmodel.model.geometry import Z_MAX, Z_MIN, disparity_validity
from sgmodel.model.network import Predictor, create_model
from sgmodel.model.render import render_views
from sgmodel.predict.inference import Reconstructor, masked
from tests.support.model_helpers import StandInEncoder


def reference_validity(d: float, fx: float, b: float, doffs: float, dmax: float) -> bool:
    """The rule, one pixel at a time in float64."""
    if not math.isfinite(d) or d <= 0 or d >= dmax or d + doffs <= 0:
        return False
    return Z_MIN <= fx * b / (d + doffs) <= Z_MAX


def test_disparity_validity_matches_the_rule():
    fx, b = torch.tensor([80.0, 200.0]), torch.tensor([0.125, 0.25])  # fx B = 10, 50 (exact): d in [1, 100], [5, 500]
    special = [math.nan, math.inf, -math.inf, 0.0, -3.0, 1.0, 0.999, 100.0, 100.01, 5.0, 4.99, 191.0, 190.99, 500.0]
    rng = np.random.default_rng(0)
    values = np.concatenate([special, rng.uniform(-5, 600, 200)]).astype(np.float32)
    d = torch.from_numpy(np.stack([values, values]))[:, None, None, :]
    for doffs in (0.0, 2.5, -1.0):
        got = disparity_validity(d, fx, b, doffs=doffs, max_disparity=191.0)
        for i in range(2):
            want = [reference_validity(float(v), float(fx[i]), float(b[i]), doffs, 191.0) for v in values]
            np.testing.assert_array_equal(got[i, 0, 0].numpy(), want, err_msg=f"item {i}, doffs {doffs}")
    # an encoder's "no match" (d = 0) stays invalid even when doffs would make d + doffs positive
    assert not disparity_validity(torch.zeros(1, 1, 1, 1), 100.0, 0.1, doffs=5.0).any()


def reference_gaussian_validity(valid: np.ndarray) -> np.ndarray:
    """Front: the pixel; back: every canvas pixel of the BACK_POOL window around it (clipped to the canvas)."""
    b, _, h, w = valid.shape
    r = BACK_POOL // 2
    back = np.zeros((b, h, w), bool)
    for i in range(b):
        for v in range(h):
            for u in range(w):
                back[i, v, u] = valid[i, 0, max(0, v - r):v + r + 1, max(0, u - r):u + r + 1].all()
    return np.concatenate([valid.reshape(b, -1), back.reshape(b, -1)], axis=1)


def test_gaussian_validity_front_and_back_layers():
    rng = np.random.default_rng(1)
    valid = rng.random((2, 1, 14, 19)) > 0.03
    valid[1] = True
    valid[1, 0, 0, 0] = False  # a corner: the window is clipped to the canvas
    got = gaussian_validity(torch.from_numpy(valid))
    np.testing.assert_array_equal(got.numpy(), reference_gaussian_validity(valid))
    assert not got[1, 14 * 19 + 4 * 19 + 4] and got[1, 14 * 19 + 5 * 19 + 5]
    np.testing.assert_array_equal(gaussian_validity(torch.from_numpy(valid), back_layer=False).numpy(),
                                  valid.reshape(2, -1))


class HoleEncoder(StandInEncoder):
    """StandInEncoder with 'no match' (d = 0) in a block and a non-finite-free saturated column."""

    def encode(self, left, right):
        out = super().encode(left, right)
        out.disparity[:, :, 2:5, 3:6] = 0.0
        out.disparity[:, :, :, -1] = 10.0 ** 6  # beyond the near clamp: z = fx B / d < Z_MIN
        return out


def test_model_prediction_valid_follows_the_canvas():
    p = ModelParams(resolution=16, padding=3)
    p.decoder.channels = p.predictor.channels = 8
    p.decoder.groups = p.predictor.groups = 4
    model = create_model(p, encoder=HoleEncoder()).eval()
    B, S, P = 2, 16, 3
    left = torch.rand(B, 3, S, S)
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]).expand(B, 3, 3)
    with torch.no_grad():
        out = Predictor(model).predict(left, left, K, torch.full((B,), 0.1))
    pixel = np.ones((B, 1, S, S), bool)
    pixel[:, :, 2:5, 3:6] = False
    pixel[:, :, :, -1] = False
    np.testing.assert_array_equal(out.pixel_valid.numpy(), pixel)
    canvas = np.pad(pixel, ((0, 0), (0, 0), (P, P), (P, P)), mode="edge")  # padding copies the pixel it replicates
    assert out.valid.shape == (B, 2 * (S + 2 * P) ** 2)
    np.testing.assert_array_equal(out.valid.numpy(), reference_gaussian_validity(canvas))
    assert out.gaussians["means"].shape[1] == out.valid.shape[1]  # training keeps N fixed


def test_baselines_make_nothing_where_the_depth_is_invalid():
    h, w = 6, 8
    K = torch.tensor([[[50.0, 0, 4], [0, 50.0, 3], [0, 0, 1]]])
    left = torch.rand(1, 3, h, w)
    z = torch.full((1, 1, h, w), 2.0)
    valid = torch.ones(1, 1, h, w, dtype=torch.bool)
    valid[..., 1:3, 2:5] = False
    same = torch.eye(4)[None, None]
    img, cov = forward_splat(left, z, K, same, K[:, None], w, h, valid=valid)
    np.testing.assert_array_equal(cov[0, 0].numpy(), valid[0].numpy())  # identity view: pixel to itself
    assert not img[0, 0][:, ~valid[0, 0]].any()
    encoder = lambda a, b: type("Out", (), {"disparity": torch.where(valid, 1.25, 0.0)})()  # noqa: E731
    encoder.max_disparity = lambda width: math.inf
    scenes = Reconstructor(method="naive-gs", encoder=encoder)(left, left, K, torch.tensor([0.1]))
    assert scenes.counts(0) == (int(valid.sum()), h * w) and len(scenes.scene(0)) == int(valid.sum())
    np.testing.assert_array_equal(scenes.pixel_valid.numpy(), valid.numpy())
    # hidden (opacity 0) renders exactly as dropped: the rasteriser skips o exp(-s) < 1/255
    g = scenes.gaussians
    keep = scenes.valid[0]
    dropped = {k: v[:, keep] for k, v in g.items()}
    views = torch.eye(4)[None, None].repeat(1, 2, 1, 1)
    views[0, 1, 0, 3] = 0.05
    a = render_views(masked(g, scenes.valid), views, K[:, None].expand(1, 2, 3, 3), w, h)[0]
    b = render_views(dropped, views, K[:, None].expand(1, 2, 3, 3), w, h)[0]
    assert torch.equal(a, b)


@pytest.mark.parametrize("method", ["naive-gs", "forward-splat"])
def test_reconstructor_runs_both_baselines_on_a_batch(method):
    left = torch.rand(3, 3, 8, 8)
    d = torch.full((3, 1, 8, 8), 2.0)
    d[1, :, :2] = -1.0
    encoder = lambda a, b: type("Out", (), {"disparity": d})()  # noqa: E731
    encoder.max_disparity = lambda width: 100.0
    K = torch.tensor([[10.0, 0, 4], [0, 10.0, 4], [0, 0, 1]]).expand(3, 3, 3)
    scenes = Reconstructor(method=method, encoder=encoder)(left, left, K, torch.full((3,), 0.2))
    assert [scenes.counts(i)[0] for i in range(3)] == [64, 48, 64]
    rgb = scenes.render(torch.eye(4).expand(3, 1, 4, 4), K[:, None], 8, 8)
    assert rgb.shape == (3, 1, 3, 8, 8)
