"""sgmodel.encoders: interface, registry, PSMNet with the real KITTI-2015 weights, SGBM, padding."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from sgmodel import weights
from sgmodel.encoders import available_encoders, create_encoder
from sgmodel.encoders.base import crop_to, pad_to_multiple
from tests.support.paths import TEST_DATA

DATA = TEST_DATA


def load_pair() -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """The bundled rendered pair (tests/data/make_stereo_pair.py): left, right [1,3,96,128] in [0,1] and
    the true disparity fx B / z [96,128] in pixels."""
    def rgb(name: str) -> torch.Tensor:
        img = cv2.cvtColor(cv2.imread(str(DATA / name)), cv2.COLOR_BGR2RGB)
        return torch.from_numpy(img).permute(2, 0, 1)[None].float() / 255

    meta = json.loads((DATA / "stereo_room.json").read_text())
    z = cv2.imread(str(DATA / "stereo_room_depth_mm.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000
    assert (z > 0).all()
    return rgb("stereo_room_left.png"), rgb("stereo_room_right.png"), meta["K"][0][0] * meta["baseline"] / z


@pytest.fixture(scope="module")
def psmnet_weights() -> Path:
    try:
        return weights.resolve("psmnet-kitti")
    except weights.WeightsError:
        try:
            return weights.fetch("psmnet-kitti")
        except weights.WeightsError as e:
            pytest.skip(f"PSMNet KITTI-2015 weights not cached and fetching them failed: {e}")


@pytest.fixture(scope="module")
def psmnet(psmnet_weights):
    torch.manual_seed(0)
    return create_encoder("psmnet-kitti", weights=str(psmnet_weights))


@pytest.fixture(scope="module")
def psmnet_on_pair(psmnet) -> torch.Tensor:
    """PSMNet's disparity [1,1,96,128] on the bundled pair (computed once: CPU time)."""
    left, right, _ = load_pair()
    return psmnet(left, right).disparity


@pytest.fixture(scope="module")
def sgbm():
    return create_encoder("sgbm")


def test_registry():
    assert {"psmnet-kitti", "sgbm", "foundation-stereo", "fast-foundation-stereo"} <= set(available_encoders())
    with pytest.raises(ValueError, match="--encoder nope: unknown encoder.*psmnet-kitti"):
        create_encoder("nope")
    with pytest.raises(ValueError, match="no weights"):
        create_encoder("sgbm", weights="x.pth")


def check_interface(enc, h: int, w: int) -> None:
    """Shapes, scales, dtype, frozen, no grads, eval after .train() on a [2,3,h,w] pair."""
    left, right, _ = load_pair()
    left = torch.cat([left, left.flip(-1)])[..., :h, :w]
    right = torch.cat([right, right.flip(-1)])[..., :h, :w]
    enc.train()
    assert not enc.training and not any(m.training for m in enc.modules())
    assert all(not p.requires_grad for p in enc.parameters())
    assert len(enc.feature_channels) == len(enc.feature_scales)
    out = enc(left, right)
    assert out.disparity.shape == (2, 1, h, w) and out.disparity.dtype == torch.float32
    assert torch.isfinite(out.disparity).all() and not out.disparity.requires_grad
    assert len(out.features) == len(enc.feature_channels)
    for f, c, s in zip(out.features, enc.feature_channels, enc.feature_scales):
        assert f.shape == (2, c, math.ceil(h / s), math.ceil(w / s)) and f.dtype == torch.float32
        assert torch.isfinite(f).all() and not f.requires_grad


def test_sgbm_interface(sgbm):
    assert sgbm.name == "sgbm" and sgbm.feature_channels == () and sgbm.weights_sha256 is None
    check_interface(sgbm, 75, 100)


def test_psmnet_interface_odd_size(psmnet):
    assert psmnet.name == "psmnet-kitti" and psmnet.feature_scales == (2, 4)
    assert psmnet.weights_sha256 == weights.SOURCES["psmnet-kitti"].sha256
    check_interface(psmnet, 75, 100)


def test_psmnet_train_keeps_batch_norm_statistics(psmnet, psmnet_on_pair):
    left, right, _ = load_pair()
    bn = psmnet.net.feature_extraction.firstconv[0][1]
    before = bn.running_mean.clone()
    a = psmnet_on_pair
    psmnet.train(True)
    b = psmnet(left, right).disparity
    assert torch.equal(bn.running_mean, before) and torch.allclose(a, b)


def test_psmnet_loads_published_weights_strictly(psmnet_weights):
    from sgmodel.encoders.psmnet import PSMNet, load_state_dict

    state = load_state_dict(psmnet_weights)
    assert len(state) == 429 and not any(k.startswith("module.") for k in state)
    net = PSMNet()
    net.load_state_dict(state, strict=True)  # raises on any missing or unexpected key or shape
    assert torch.equal(net.dres4.conv6[0].weight, state["dres4.conv6.0.weight"])


def test_psmnet_disparity_on_rendered_pair(psmnet_on_pair):
    _, _, truth = load_pair()
    d = psmnet_on_pair[0, 0].numpy()
    assert np.isfinite(d).all() and (d > 0).mean() > 0.99
    ratio = np.median(d) / np.median(truth)
    assert 0.67 < ratio < 1.5, f"median disparity {np.median(d):.2f} px vs true {np.median(truth):.2f} px"
    assert np.median(np.abs(d - truth)) < 2.0


def test_sgbm_disparity_on_rendered_pair(sgbm):
    left, right, truth = load_pair()
    d = sgbm(left, right).disparity[0, 0].numpy()
    valid = d > 0
    assert valid.mean() > 0.8 and (d >= 0).all()
    assert np.median(np.abs(d - truth)[valid]) < 0.5


def test_sgbm_parameters_scale_with_width():
    from sgmodel.encoders.sgbm import sgbm_parameters

    for width, nd in ((100, 32), (128, 32), (256, 64), (1242, 320)):
        p = sgbm_parameters(width)
        assert p["numDisparities"] == nd and p["numDisparities"] % 16 == 0
        assert p["P2"] > p["P1"] > 0 and p["blockSize"] % 2 == 1


def test_missing_weights_message(tmp_path, monkeypatch):
    monkeypatch.setenv("SGMODEL_CACHE", str(tmp_path / "empty-cache"))
    with pytest.raises(weights.WeightsError) as e:
        create_encoder("psmnet-kitti")
    assert "sgmodel weights fetch psmnet-kitti" in str(e.value) and "--encoder-weights PATH" in str(e.value)
    with pytest.raises(weights.WeightsError, match="no such file"):
        create_encoder("psmnet-kitti", weights=str(tmp_path / "absent.tar"))
    bad = tmp_path / "bad.tar"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(weights.WeightsError, match="bad.tar: not a readable PSMNet checkpoint"):
        create_encoder("psmnet-kitti", weights=str(bad))
    wrong = tmp_path / "wrong.tar"
    torch.save({"state_dict": {"module.x": torch.zeros(1)}}, wrong)
    with pytest.raises(weights.WeightsError, match="does not match PSMNet"):
        create_encoder("psmnet-kitti", weights=str(wrong))


def test_pad_and_crop_odd_sizes():
    x = torch.rand(2, 3, 75, 100, dtype=torch.float64)
    p = pad_to_multiple(x, 16)
    assert p.shape == (2, 3, 80, 112)
    assert torch.equal(p[..., :75, :100], x)
    assert torch.equal(p[..., 75:, :100], x[..., 74:75, :].expand(2, 3, 5, 100))  # last row repeated
    assert torch.equal(p[..., :75, 100:], x[..., :, 99:100].expand(2, 3, 75, 12))  # last column repeated
    assert torch.equal(p[..., 75:, 100:], x[..., 74:75, 99:100].expand(2, 3, 5, 12))
    assert torch.equal(crop_to(p, 75, 100), x)
    assert crop_to(torch.zeros(1, 4, 20, 28), 75, 100, 4).shape == (1, 4, 19, 25)
    assert pad_to_multiple(x[..., :64, :96], 16).shape[-2:] == (64, 96)
    assert pad_to_multiple(x, 16, min_size=128).shape[-2:] == (128, 128)


def test_bad_pair_shapes(sgbm):
    with pytest.raises(ValueError, match="left .* and right .* differ"):
        sgbm(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 9))
    with pytest.raises(ValueError, match=r"expected \[B,3,H,W\]"):
        sgbm(torch.zeros(3, 8, 8), torch.zeros(3, 8, 8))
