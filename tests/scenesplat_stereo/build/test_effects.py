"""effects.py: camera effects on the stereo inputs, off by default, deterministic per (seed, key)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenesplat_stereo.build import effects as fx
from scenesplat_stereo.build.effects import CameraEffects

H, W = 24, 32
K = torch.tensor([[[20.0, 0.0, 16.0], [0.0, 20.0, 12.0], [0.0, 0.0, 1.0]]])


def flat(value: float = 0.5, p: int = 1) -> torch.Tensor:
    return torch.full((p, 2, H, W, 3), value)


def test_parse():
    assert CameraEffects.parse(None) is None
    assert CameraEffects.parse("") is None
    assert CameraEffects.parse("none") is None
    e = CameraEffects.parse("noise, Exposure", seed=3)
    assert (e.noise, e.vignetting, e.exposure, e.seed) == (True, False, True, 3)
    assert e.names == ["noise", "exposure"]
    with pytest.raises(ValueError, match="blur"):
        CameraEffects.parse("noise,blur")


def test_parameters_deterministic_per_seed_and_key_and_independent_of_other_effects():
    a = CameraEffects(noise=True, vignetting=True, exposure=True, seed=1)
    assert a.sample("s__000001") == a.sample("s__000001")
    assert a.sample("s__000001") != a.sample("s__000002")
    assert a.sample("s__000001") != CameraEffects(noise=True, vignetting=True, exposure=True, seed=2).sample("s__000001")
    only_exposure = CameraEffects(exposure=True, seed=1).sample("s__000001")
    assert only_exposure.ev == a.sample("s__000001").ev
    assert (only_exposure.vignetting, only_exposure.shot_gain, only_exposure.read_std) == (0.0, 0.0, 0.0)
    out1 = a.apply(flat(), ["k__000000"], K)
    out2 = a.apply(flat(), ["k__000000"], K)
    assert torch.equal(out1, out2)


def test_exposure_gain_and_pair_mismatch():
    e = CameraEffects(exposure=True, seed=0)
    img = torch.rand(1, 2, H, W, 3, generator=torch.Generator().manual_seed(0)) * 0.4
    evs = []
    for i in range(50):
        key = f"x__{i:06d}"
        ev_l, ev_r = e.sample(key).ev
        evs.append(ev_l)
        assert abs(ev_l) <= fx.EXPOSURE_EV_RANGE and abs(ev_r - ev_l) <= fx.EXPOSURE_PAIR_MISMATCH_EV
        out = e.apply(img, [key], K)
        want = torch.stack([(img[0, 0] * 2.0**ev_l).clamp(max=1.0), (img[0, 1] * 2.0**ev_r).clamp(max=1.0)])
        assert torch.allclose(out[0], want, atol=1e-6)
    assert np.std(evs) > 0.1  # actually jittered


def test_vignetting_is_the_cos4_law():
    e = CameraEffects(vignetting=True, seed=0)
    key = "v__000000"
    s = e.sample(key).vignetting
    out = e.apply(flat(1.0), [key], K)[0, 0, :, :, 0]
    for v, u in [(0, 0), (12, 16), (23, 31), (5, 20)]:
        tan_x, tan_y = (u + 0.5 - 16.0) / 20.0, (v + 0.5 - 12.0) / 20.0
        cos_theta = 1.0 / math.sqrt(1.0 + tan_x**2 + tan_y**2)
        assert out[v, u].item() == pytest.approx(cos_theta ** (4 * s), rel=1e-5)
    assert out[12, 16] > out[0, 0]  # brightest at the principal point


def test_noise_statistics():
    e = CameraEffects(noise=True, seed=0)
    img = flat(0.5, p=1).repeat(1, 1, 4, 4, 1)  # 96x128 pixels for statistics
    k = torch.tensor([[[80.0, 0.0, 64.0], [0.0, 80.0, 48.0], [0.0, 0.0, 1.0]]])
    key = "n__000000"
    p = e.sample(key)
    out = e.apply(img, [key], k)
    resid = (out - img)[0]
    want_std = math.sqrt(p.shot_gain * 0.5 + p.read_std**2)
    assert resid.mean().abs().item() < 4 * want_std / math.sqrt(resid.numel())
    assert resid.std().item() == pytest.approx(want_std, rel=0.05)
    assert not torch.equal(resid[0], resid[1])  # independent draws per camera


def test_shape_checked():
    with pytest.raises(ValueError):
        CameraEffects(noise=True).apply(torch.zeros(1, 3, H, W, 3), ["a"], K)
