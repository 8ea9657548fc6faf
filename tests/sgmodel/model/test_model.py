"""The model's rooms: canvas, decoder, predictor, the assembled model, gradients and bad input."""

from __future__ import annotations

import pytest
import torch

from sgmodel.config import ComposerParams, DecoderParams, ModelParams, PredictorParams
from sgmodel.model import canvas
from sgmodel.model import predictor as predictor_module
from sgmodel.model.decoder import DPTDecoder
from sgmodel.model.network import create_model
from sgmodel.model.predictor import CHANNELS, LAYER_CHANNELS, GaussianPredictor
from sgmodel.model.render import render_views
from tests.support.model_helpers import StandInEncoder, textured_batch


def small_params(**changes) -> ModelParams:
    p = ModelParams(resolution=32, padding=4, decoder=DecoderParams(channels=16, groups=4),
                    predictor=PredictorParams(channels=16, groups=4))
    for k, v in changes.items():
        setattr(p, k, v)
    return p


def test_canvas_intrinsics_shift_principal_point_only():
    K = torch.tensor([[[100.0, 0, 31.5], [0, 90.0, 20.25], [0, 0, 1]]])
    Kc = canvas.canvas_intrinsics(K, 16)
    assert torch.equal(Kc[0, 0, 0], K[0, 0, 0]) and torch.equal(Kc[0, 1, 1], K[0, 1, 1])
    assert Kc[0, 0, 2].item() == 47.5 and Kc[0, 1, 2].item() == 36.25
    # a pixel's ray is unchanged by the canvas: canvas pixel (u + P, v + P) is image pixel (u, v)
    ray = torch.linalg.inv(K[0]) @ torch.tensor([10.5, 7.5, 1.0])
    ray_c = torch.linalg.inv(Kc[0]) @ torch.tensor([26.5, 23.5, 1.0])
    assert torch.allclose(ray, ray_c, atol=1e-6)


def test_canvas_extend_replicates_edges():
    x = torch.arange(12.0).view(1, 1, 3, 4)
    y = canvas.extend(x, 2)
    assert y.shape == (1, 1, 7, 8)
    assert torch.equal(y[0, 0, 2:5, 2:6], x[0, 0])
    assert torch.equal(y[0, 0, 0, :2], torch.full((2,), x[0, 0, 0, 0].item()))
    assert torch.equal(y[0, 0, -1, -2:], torch.full((2,), x[0, 0, -1, -1].item()))
    assert canvas.extend(x, 0) is x


@pytest.mark.parametrize("features", [True, False])
def test_decoder_shapes(features):
    B, S = 2, 32
    rgb, z = torch.rand(B, 3, S, S), torch.rand(B, 1, S, S) * 5 + 0.1
    if features:
        dec = DPTDecoder((6, 8), (2, 4), 16, 4, rgbd=True, rgbd_scales=(2, 4, 8))
        feats = [torch.rand(B, 6, S // 2, S // 2), torch.rand(B, 8, S // 4, S // 4)]
    else:
        dec = DPTDecoder((), (), 16, 4, rgbd=True, rgbd_scales=(2, 4, 8))
        feats = []
    phi = dec(feats, rgb, z)
    assert phi.shape == (B, 16, S, S) and torch.isfinite(phi).all()
    unbiased, bias = dec.without_last_bias(feats, rgb, z)  # the predictor adds that bias as it copies phi
    assert bias is dec.head[2].bias
    torch.testing.assert_close(unbiased + bias[:, None, None], phi, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="RGB-D"):
        DPTDecoder((), (), 16, 4, rgbd=False, rgbd_scales=(2, 4))


def test_predictor_zero_initialised_heads():
    pred = GaussianPredictor(PredictorParams(channels=16, groups=4), descriptor_channels=16, rgbd=True)
    Hc = 20
    front, back, dz = pred(torch.rand(2, 3, Hc, Hc), torch.rand(2, 1, Hc, Hc) + 1, torch.rand(2, 16, Hc, Hc))
    assert front.shape == back.shape == (2, LAYER_CHANNELS, Hc, Hc) and dz.shape == (2, 1, Hc, Hc)
    for layer in (front, back):
        assert torch.all(layer[:, CHANNELS["scale"]] == 0) and torch.all(layer[:, CHANNELS["sh"]] == 0)
        for name in ("opacity", "offset", "quat"):  # small and non-zero
            v = layer[:, CHANNELS[name]].abs()
            assert 0 < v.max() < 0.5, name
    assert torch.all(dz == 0)
    assert sorted((s.start, s.stop) for s in CHANNELS.values()) == [(0, 1), (1, 3), (3, 6), (6, 10), (10, 37)]


@pytest.mark.parametrize("rgbd", [True, False])
def test_predictor_adds_phis_bias_as_it_copies_phi(rgbd, monkeypatch):
    """``phi_bias`` is phi's: the predictor gives (in float64 here) what it gives for phi with the bias added."""
    monkeypatch.setattr(predictor_module, "compute_dtype", lambda device: torch.float64)
    pred = GaussianPredictor(PredictorParams(channels=16, groups=4), descriptor_channels=12, rgbd=rgbd).double()
    with torch.no_grad():
        for t in pred.parameters():
            t.normal_(std=0.2)
    rgb, z = torch.rand(2, 3, 14, 18, dtype=torch.float64), 1 + torch.rand(2, 1, 14, 18, dtype=torch.float64)
    phi, bias = torch.randn(2, 12, 8, 12, dtype=torch.float64), torch.randn(12, dtype=torch.float64)
    want = pred(rgb, z, phi + bias[:, None, None], phi_padding=3)
    got = pred(rgb, z, phi, phi_padding=3, phi_bias=bias)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_predictor_without_back_layer_has_no_back_branch():
    pred = GaussianPredictor(PredictorParams(channels=16, groups=4), 0, rgbd=True, back_layer=False)
    front, back, dz = pred(torch.rand(1, 3, 8, 8), torch.ones(1, 1, 8, 8), None)
    assert back is None and dz is None and front.shape == (1, 37, 8, 8)
    assert not any(n.startswith(("back", "dz")) for n, _ in pred.named_parameters())


def test_model_outputs_and_initial_gaussians():
    batch = textured_batch(B=2, S=32)
    model = create_model(small_params(), encoder=StandInEncoder(disparity=8.0))
    out = model(batch["left"], batch["right"], batch["K"], batch["baseline"])
    Hc = 32 + 2 * 4
    g = out.gaussians
    assert g["means"].shape == (2, 2 * Hc * Hc, 3) and g["sh"].shape == (2, 2 * Hc * Hc, 9, 3)
    # front layer at the stereo depth z = fx B / d = 32 * 0.1 / 8 = 0.4 m
    assert torch.allclose(out.depth, torch.full_like(out.depth, 0.4))
    assert torch.allclose(g["means"][:, : Hc * Hc, 2], torch.full((2, Hc * Hc), 0.4), atol=1e-6)
    # the encoder is frozen and outside the module tree
    ids = {id(p) for p in model.parameters()}
    assert ids and not any(id(p) in ids for p in model.encoder.parameters())
    assert not any("encoder" in k for k in model.state_dict())
    assert all(not p.requires_grad for p in model.encoder.parameters())


def test_gradients_reach_every_trainable_parameter_through_the_rasteriser():
    batch = textured_batch(B=2, T=2, S=32)
    model = create_model(small_params(), encoder=StandInEncoder())
    opt = torch.optim.SGD(model.parameters(), lr=1e-2)

    def loss_and_grads():
        opt.zero_grad()
        out = model(batch["left"], batch["right"], batch["K"], batch["baseline"])
        rgb, _ = render_views(out.gaussians, batch["target_viewmats"], batch["target_Ks"], 32, 32)
        ((rgb - batch["targets"]) ** 2).mean().backward()
        return [n for n, p in model.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()
                or p.grad.abs().sum() == 0]

    # the zero-initialised heads pass no gradient back on the very first step (their weights are zero),
    # except into the heads themselves; after one update every parameter receives one
    first = loss_and_grads()
    assert first and all(n.startswith("predictor.dz.") and not n.startswith("predictor.dz.3") for n in first), first
    opt.step()
    assert loss_and_grads() == []
    assert all(p.grad is None for p in model.encoder.parameters())


@pytest.mark.parametrize("change", [dict(descriptor=False), dict(rgbd=False),
                                    dict(composer=ComposerParams(back_layer=False)),
                                    dict(composer=ComposerParams(edge_mask="soft")),
                                    dict(composer=ComposerParams(composer=False)), dict(padding=0)])
def test_ablation_variants_build_and_run(change):
    batch = textured_batch(B=1, S=32)
    model = create_model(small_params(**change), encoder=StandInEncoder())
    g = model(batch["left"], batch["right"], batch["K"], batch["baseline"]).gaussians
    layers = 1 if "composer" in change and not change["composer"].back_layer else 2
    Hc = 32 + 2 * model.params.padding
    assert g["means"].shape[1] == layers * Hc * Hc
    assert all(torch.isfinite(v).all() for v in g.values())


def _K_with(item: int, row: int, col: int, value: float) -> torch.Tensor:
    K = textured_batch(B=2, S=32)["K"].clone()
    K[item, row, col] = value
    return K


@pytest.mark.parametrize("field,value,match", [
    ("baseline", torch.zeros(2), r"baseline must be finite and > 0 metres: not so for batch items \[0, 1\]"),
    ("baseline", torch.tensor([0.1, float("nan")]), r"baseline .* batch items \[1\]"),
    ("baseline", torch.tensor([float("inf"), 0.1]), r"baseline .* batch items \[0\]"),
    ("baseline", torch.full((3,), 0.1), r"baseline must be \[B\] = \[2\], got \[3\]"),
    ("K", torch.zeros(2, 3, 3), r"positive focal lengths.*: not so for batch items \[0, 1\]"),
    ("K", _K_with(1, 1, 1, -5.0), r"focal lengths.*: not so for batch items \[1\]"),
    ("K", _K_with(0, 0, 2, float("nan")), r"K must be finite.* batch items \[0\]"),
    ("K", _K_with(1, 2, 2, 0.0), r"the last row 0 0 1: not so for batch items \[1\]"),
    ("K", _K_with(0, 2, 0, 1e-3), r"the last row 0 0 1: not so for batch items \[0\]"),
    ("K", torch.eye(3).expand(1, 3, 3), r"K must be \[B, 3, 3\] = \[2, 3, 3\], got \[1, 3, 3\]"),
    ("left", torch.rand(2, 3, 8, 8), "too small|same"),
])
def test_bad_inputs_are_named(field, value, match):
    batch = textured_batch(B=2, S=32)
    model = create_model(small_params(), encoder=StandInEncoder())
    batch[field] = value
    if field == "left":
        batch["right"] = value
    with pytest.raises(ValueError, match=match):
        model(batch["left"], batch["right"], batch["K"], batch["baseline"])


def test_non_finite_disparity_is_an_error():
    batch = textured_batch(B=2, S=32)
    model = create_model(small_params(), encoder=StandInEncoder(disparity=float("nan")))
    with pytest.raises(ValueError, match="non-finite disparity"):
        model(batch["left"], batch["right"], batch["K"], batch["baseline"])


def test_invalid_configurations_are_refused():
    with pytest.raises(ValueError, match="resolution"):
        small_params(resolution=30).validate()
    with pytest.raises(ValueError, match="--edge-mask .maybe.: must be one of"):
        small_params(composer=ComposerParams(edge_mask="maybe")).validate()
    with pytest.raises(ValueError, match="--edge-mask hard: .* --no-back-layer"):
        small_params(composer=ComposerParams(edge_mask="hard", back_layer=False)).validate()
    with pytest.raises(ValueError, match="multiple"):
        small_params(decoder=DecoderParams(channels=10, groups=4)).validate()
    assert ModelParams.from_dict(small_params().to_dict()) == small_params()
