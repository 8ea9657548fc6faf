"""The model shipped in the package (issue 38): it loads, its file is the one recorded (sha256), a changed file is
refused, and ``sgmodel predict`` runs it on a small real-size pair without ``--checkpoint`` and says so."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import pytest

from sgmodel import weights
from sgmodel.cli import main as sgmodel_main
from sgmodel.model.network import load_predictor
from tests.support.paths import REPO, TEST_DATA

SHIPPED_FILE = REPO / "sgmodel" / "model" / "shipped" / "stereogaussians-default.pt"


def test_the_shipped_file_is_the_recorded_one_and_small():
    assert hashlib.sha256(SHIPPED_FILE.read_bytes()).hexdigest() == weights.SHIPPED.sha256
    assert weights.shipped_model() == SHIPPED_FILE.resolve()
    assert SHIPPED_FILE.stat().st_size <= 16 * 2**20


def test_a_changed_shipped_file_is_refused(monkeypatch):
    monkeypatch.setattr(weights, "SHIPPED", dataclasses.replace(weights.SHIPPED, sha256="0" * 64))
    with pytest.raises(weights.WeightsError, match="altered; reinstall"):
        weights.checkpoint_path(None)


def test_the_shipped_model_loads_with_its_encoder():
    pytest.importorskip("sgmodel.encoders.psmnet")
    try:
        predictor = load_predictor(weights.checkpoint_path("default"), "cpu")
    except weights.WeightsError as e:
        pytest.skip(f"PSMNet weights not fetched ({e})")
    assert predictor.model.encoder.name == "psmnet-kitti" and predictor.resolution == 256
    assert sum(p.numel() for p in predictor.model.parameters() if p.requires_grad) == 2_643_403
    # float32 by default, though trained under bf16 autocast; bf16 autocast only on CUDA and only with --amp
    assert not predictor.amp and predictor.precision("cuda") == "float32"
    bf16 = load_predictor(weights.checkpoint_path("default"), "cpu", amp=True)
    assert bf16.precision("cuda") == "bf16 autocast" and bf16.precision("cpu") == "float32"


def test_predict_runs_the_shipped_model_without_a_checkpoint(tmp_path, capsys):
    if not weights.cached_path("psmnet-kitti").is_file():
        pytest.skip("PSMNet weights not fetched: `sgmodel weights fetch psmnet-kitti`")
    meta = json.loads((TEST_DATA / "stereo_room.json").read_text())
    K = meta["K"]
    intrinsics = f"{K[0][0]},{K[1][1]},{K[0][2]},{K[1][2]}"
    out = tmp_path / "out"
    rc = sgmodel_main(["predict", "--left", TEST_DATA / "stereo_room_left.png", "--right",
                       TEST_DATA / "stereo_room_right.png", "--intrinsics", intrinsics, "--baseline",
                       str(meta["baseline"]), "--resolution", "64", "--out", out, "--device", "cpu"])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    assert "model: the shipped model 'default'" in printed and ", float32" in printed
    assert (out / "scene.ply").is_file() and (out / "views" / "center.png").is_file()


def test_eval_measures_the_shipped_model_without_a_checkpoint_and_names_it():
    import argparse

    from sgmodel.evaluation import evaluate

    args = argparse.Namespace(checkpoint=None, method=None)
    assert evaluate.methods_of(args) == ["checkpoint"]
    assert evaluate.methods_of(argparse.Namespace(checkpoint=None, method=["naive-gs"])) == ["naive-gs"]
    if not weights.cached_path("psmnet-kitti").is_file():
        pytest.skip("PSMNet weights not fetched: `sgmodel weights fetch psmnet-kitti`")
    method = evaluate.checkpoint_method(None, "cpu")
    assert method.name.startswith("the shipped model 'default' (sha256 61a57c55") and method.precision == "float32"


def test_weight_rounding_moves_each_weight_within_half_a_bf16_ulp():
    """scripts/checks/weight_rounding.py: the ulp is bf16's spacing (against nextafter in bf16), and a moved
    weight stays within half of it, so it rounds back to the stored bf16 value."""
    import torch

    from scripts.checks.weight_rounding import bf16_ulp, moved

    scale = torch.logspace(-6, 3, 10_000, dtype=torch.float64)
    w = (torch.randn(10_000, dtype=torch.float64) * scale).to(torch.bfloat16)
    up = torch.nextafter(w.abs(), torch.tensor(float("inf"), dtype=torch.bfloat16))
    assert torch.equal(bf16_ulp(w), (up.float() - w.abs().float()))
    out = moved({"model": {"w": w, "step": 3}}, seed=0)["model"]
    assert out["step"] == 3 and out["w"].dtype == torch.float32
    assert ((out["w"] - w.float()).abs() <= bf16_ulp(w) / 2).all()
    assert (out["w"] != w.float()).float().mean() > 0.99
