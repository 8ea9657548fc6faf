"""The encoder flags (sgmodel/encoders/flags.py) and every command that makes an encoder, run through the command
line with the FoundationStereo stand-ins on the demo dataset: eval (both baselines), bench encoders (several
encoders, each with its own weights and checkout), train, eval and predict of the checkpoint, ablate; bad flags
exit 2 with one line."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from scenesplat_stereo.shards.encode import encode_png
from sgmodel.cli import build_parser
from sgmodel.config import EncoderParams
from sgmodel.encoders import EncoderFlagError
from sgmodel.encoders.flags import encoder_label, merge_encoder, parse_encoder_spec
from tests.support.foundation_standins import FFS_REPO, FS_REPO, save_ffs_model, save_fs_checkpoint
from tests.support.model_helpers import sgmodel_status

TINY = ["--resolution", "32", "--padding", "2", "--decoder-channels", "16", "--predictor-channels", "16"]
SCHEDULE = ["--steps", "2", "--batch-size", "2", "--targets", "2", "--val-every", "2", "--val-samples", "2",
            "--workers", "0", "--no-progress", "--device", "cpu"]


@pytest.fixture(scope="module")
def releases(tmp_path_factory) -> dict[str, list[str]]:
    """The encoder flags of each stand-in release, by encoder name."""
    base = tmp_path_factory.mktemp("releases")
    fs = save_fs_checkpoint(base / "FoundationStereo" / "23-51-11")
    ffs = save_ffs_model(base / "Fast-FoundationStereo" / "23-36-37" / "model_best_bp2_serialize.pth")
    return {"foundation-stereo": ["--encoder", "foundation-stereo", "--encoder-weights", fs, "--encoder-repo", FS_REPO],
            "fast-foundation-stereo": ["--encoder", "fast-foundation-stereo", "--encoder-weights", ffs,
                                       "--encoder-repo", FFS_REPO]}


def spec(flags: list) -> str:
    """--encoder X --encoder-weights W --encoder-repo R -> 'X,weights=W,repo=R' (sgmodel bench encoders)."""
    return f"{flags[1]},weights={flags[3]},repo={flags[5]}"


def test_encoder_specs():
    assert parse_encoder_spec("sgbm") == EncoderParams("sgbm", None, None)
    assert parse_encoder_spec("foundation-stereo,weights=/w/m.pth,repo=/r") == EncoderParams(
        "foundation-stereo", "/w/m.pth", "/r")
    assert parse_encoder_spec("fast-foundation-stereo,repo=R") == EncoderParams("fast-foundation-stereo", None, "R")
    for bad in ("", ",weights=x", "x,weight=w", "x,weights=", "x,weights=a,weights=b", "x,repo"):
        with pytest.raises(EncoderFlagError, match="--encoders .*NAME\\[,weights=PATH\\]\\[,repo=PATH\\]"):
            parse_encoder_spec(bad)
    a = EncoderParams("fast-foundation-stereo", "w/23-36-37/m.pth")
    b = EncoderParams("fast-foundation-stereo", "w/x/m.pth")
    assert encoder_label(a, [a, b]) == "fast-foundation-stereo (23-36-37/m.pth)"
    assert encoder_label(a, [a, EncoderParams("sgbm")]) == "fast-foundation-stereo"


def test_flags_over_a_preset_or_a_checkpoint():
    base = EncoderParams("psmnet-kitti", "w.tar", None)
    assert merge_encoder(base) == base and merge_encoder(None) == EncoderParams("psmnet-kitti")
    assert merge_encoder(base, weights="v.tar") == EncoderParams("psmnet-kitti", "v.tar", None)
    assert merge_encoder(base, "sgbm") == EncoderParams("sgbm")  # another encoder: nothing of the preset's carries over
    assert merge_encoder(base, "psmnet-kitti", checkpoint="c.pt") == base
    assert merge_encoder(EncoderParams("foundation-stereo", "a", "b"), repo="c", checkpoint="c.pt").repo == "c"
    with pytest.raises(EncoderFlagError, match="--encoder sgbm: checkpoint c.pt was trained with encoder 'psmnet"):
        merge_encoder(base, "sgbm", checkpoint="c.pt")


@pytest.mark.parametrize("command", [["train", "--data", "d", "--out", "o"], ["ablate", "--data", "d", "--out", "o"],
                                     ["eval", "--data", "d", "--out", "o", "--method", "naive-gs"],
                                     ["predict", "--left", "l", "--right", "r", "--out", "o", "--method", "naive-gs"],
                                     ["bench", "train"], ["bench", "predict"],
                                     ["encode", "--data", "d", "--out", "o"]])
def test_every_command_that_makes_an_encoder_has_the_three_flags(command):
    args = build_parser().parse_args(command + ["--encoder", "e", "--encoder-weights", "w", "--encoder-repo", "r"])
    assert (args.encoder, args.encoder_weights, args.encoder_repo) == ("e", "w", "r")


def test_eval_baselines_with_both_encoders(demo_dataset, releases, tmp_path):
    for (name, flags), method in zip(releases.items(), ("naive-gs", "forward-splat")):
        out = tmp_path / name
        assert sgmodel_status(["eval", "--data", demo_dataset, "--method", method, *flags, "--resolution", 32, "--out", out,
                    "--device", "cpu", "--no-progress"]) == 0
        result = json.loads((out / "metrics.json").read_text())
        assert result["encoder"] == name and result["method"] == method and result["targets"] == 20


def test_bench_encoders_compares_several_each_with_its_own_release(demo_dataset, releases, tmp_path, capsys):
    out = tmp_path / "encoders.md"
    assert sgmodel_status(["bench", "encoders", "--data", demo_dataset, "--encoders", spec(releases["fast-foundation-stereo"]),
                spec(releases["foundation-stereo"]), "sgbm", "--resolution", 32, "--device", "cpu",
                "--out", out]) == 0
    rows = [line.split("|")[1].strip() for line in out.read_text().splitlines() if line.startswith("| ")]
    assert rows == ["encoder", "fast-foundation-stereo", "foundation-stereo", "sgbm"]


def test_train_eval_predict_ablate_with_foundation_encoders(demo_dataset, releases, tmp_path, capsys):
    ffs, fs = releases["fast-foundation-stereo"], releases["foundation-stereo"]
    run = tmp_path / "run"
    assert sgmodel_status(["train", "--data", demo_dataset, "--out", run, *ffs, *TINY, *SCHEDULE]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["encoder"]["name"] == "fast-foundation-stereo" and len(config["encoder"]["weights_sha256"]) == 64
    best = run / "checkpoints" / "best.pt"
    assert sgmodel_status(["eval", "--data", demo_dataset, "--checkpoint", best, "--out", tmp_path / "eval", "--device", "cpu",
                "--no-progress", "--encoder-repo", FFS_REPO]) == 0
    assert json.loads((tmp_path / "eval" / "metrics.json").read_text())["encoder"] == "fast-foundation-stereo"
    img = cv2.resize((np.random.default_rng(0).random((8, 16, 3)) * 255).astype(np.uint8), (52, 32),
                     interpolation=cv2.INTER_CUBIC)  # a textured pair 2 px apart (the same image twice has no depth)
    for name, x0 in (("l.png", 2), ("r.png", 4)):
        (tmp_path / name).write_bytes(encode_png(img[:, x0:x0 + 48]))
    pair = ["--left", tmp_path / "l.png", "--right", tmp_path / "r.png", "--intrinsics", "50,50,24,16",
            "--baseline", "0.1", "--device", "cpu"]
    assert sgmodel_status(["predict", *pair, "--checkpoint", best, "--out", tmp_path / "scene"]) == 0
    assert (tmp_path / "scene" / "scene.ply").is_file()
    capsys.readouterr()
    assert sgmodel_status(["predict", *pair, "--checkpoint", best, "--out", tmp_path / "other", *fs]) == 2
    err = capsys.readouterr().err
    assert "--encoder foundation-stereo: checkpoint" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "other").exists()
    assert sgmodel_status(["ablate", "--data", demo_dataset, "--out", tmp_path / "ablate", "--only", "default", *fs, *TINY,
                *SCHEDULE]) == 0
    table = (tmp_path / "ablate" / "table.md").read_text()
    assert "encoder foundation-stereo" in table and "| naive-gs |" in table and "| forward-splat |" in table


def test_foundation_stereo_outputs_cached_once_then_trained_and_ablated_from(demo_dataset, releases, tmp_path, capsys):
    """The paper's setting (FoundationStereo frozen) through the encoder cache: `encode`, then `train` and
    `ablate` read it; the other release's encoder is refused that cache before anything is written."""
    ffs, fs = releases["fast-foundation-stereo"], releases["foundation-stereo"]
    cache = tmp_path / "cache"
    assert sgmodel_status(["encode", "--data", demo_dataset, "--out", cache, *fs, "--resolution", 32, "--device", "cpu",
                           "--workers", 0, "--no-progress"]) == 0
    info = json.loads((cache / "cache.json").read_text())
    assert info["encoder"]["name"] == "foundation-stereo" and len(info["encoder"]["weights_sha256"]) == 64
    assert sgmodel_status(["train", "--data", demo_dataset, "--out", tmp_path / "run", *fs, *TINY, *SCHEDULE,
                           "--encoder-cache", cache]) == 0
    assert sgmodel_status(["ablate", "--data", demo_dataset, "--out", tmp_path / "ablate", "--only", "default", *fs,
                           *TINY, *SCHEDULE, "--encoder-cache", cache]) == 0
    capsys.readouterr()
    assert sgmodel_status(["train", "--data", demo_dataset, "--out", tmp_path / "other", *ffs, *TINY, *SCHEDULE,
                           "--encoder-cache", cache]) == 2
    assert "field 'encoder'" in capsys.readouterr().err and not (tmp_path / "other").exists()


@pytest.mark.parametrize("argv,message", [
    (["eval", "--method", "naive-gs", "--encoder", "foundation-stereo"], "needs your checkout of NVlabs/Foundation"),
    (["eval", "--method", "naive-gs", "--encoder", "foundation-stereo", "--encoder-repo", "{tmp}"],
     "--encoder-repo {tmp}: no core/foundation_stereo.py there"),
    (["eval", "--method", "naive-gs", "--encoder", "sgbm", "--encoder-repo", "{tmp}"], "--encoder-repo: encoder 'sgbm"),
    (["bench", "encoders", "--encoders", "sgbm,weight=x"], "--encoders 'sgbm,weight=x'"),
    (["bench", "encoders", "--encoders", "sgbm", "nope"], "--encoder nope: unknown encoder"),
])
def test_bad_encoder_flags_exit_2_with_one_line(demo_dataset, tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    common = ["--data", demo_dataset, "--out", out, "--device", "cpu"]
    common += ["--no-progress"] if argv[0] == "eval" else []
    assert sgmodel_status([a.format(tmp=tmp_path) for a in argv] + common) == 2
    err = capsys.readouterr().err
    assert message.format(tmp=tmp_path) in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()
