"""The encoder cache (``sgmodel encode``, ``train --encoder-cache``): a step that reads the cache computes what a
step that runs the encoder computes; the cache resumes after an interruption to the same bytes; a cache that
does not fit the run, or is damaged, is refused naming the file and field, and nothing is written."""

from __future__ import annotations

import copy
import hashlib
import io
import json
import re
import shutil

import numpy as np
import pytest
import torch

from scenesplat_stereo.common.commandline import Interrupted
from sgmodel.data import encoder_cache as cache_mod
from sgmodel.data.loader import DataError, make_loader
from sgmodel.encoders import ENCODERS
from sgmodel.model.network import create_model, encode_pair
from sgmodel.train import encode_cache as encode_mod
from sgmodel.train import loop as train_mod
from sgmodel.train import step as step_mod
from sgmodel.train.losses import create_objective
from tests.sgmodel.train.test_train import tiny_model_params, tiny_schedule
from tests.support.model_helpers import StandInEncoder, sgmodel_status

S = 32


def stand_in_params():
    params = tiny_model_params()
    params.encoder.name = "stand-in"
    return params


@pytest.fixture
def stand_in(monkeypatch):
    """The stand-in encoder (features at 1/2 and 1/4) in the registry, so ``train`` can build it by name."""
    monkeypatch.setitem(ENCODERS, "stand-in", lambda weights, repo: StandInEncoder())


@pytest.fixture(scope="module")
def cache(demo_dataset, tmp_path_factory):
    """The stand-in encoder's cache of the demo dataset at S = 32 (float32), in chunks of 3 pairs (the
    dataset's shards hold 4 and 2, so chunks never line up with training batches)."""
    out = tmp_path_factory.mktemp("cache") / "cache"
    encode_mod.encode_dataset(demo_dataset, out, StandInEncoder(), S, "float32", ["train", "val"], "cpu",
                              batch_size=3, workers=0, progress=False)
    return out


def opened(cache, demo_dataset, **changes):
    settings = dict(encoder=StandInEncoder(), resolution=S, precision="float32", splits=["train", "val"]) | changes
    return cache_mod.open_cache(cache, demo_dataset, settings["encoder"], settings["resolution"],
                                settings["precision"], settings["splits"])


def test_cached_batches_carry_what_the_encoder_computes(cache, demo_dataset):
    encoder = StandInEncoder()
    with_cache = make_loader(demo_dataset, "train", 4, S, 2, seed=3, num_workers=2,  # the cache goes to workers
                             cache=opened(cache, demo_dataset))
    without = make_loader(demo_dataset, "train", 4, S, 2, seed=3)
    for _, a, b in zip(range(4), with_cache, without):  # 16 samples: past the end of an epoch of 12
        assert a["keys"] == b["keys"]
        for name in ("left", "right", "targets", "target_viewmats"):
            assert torch.equal(a[name], b[name]), name
        disparity, features = encode_pair(encoder, b["left"], b["right"])
        assert torch.equal(a["encoder_disparity"], disparity)
        for got, want in zip(a["encoder_features"], features, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)  # batched 3 vs 4: the same sums


def test_a_step_from_the_cache_equals_a_step_that_runs_the_encoder(cache, demo_dataset):
    batch = next(iter(make_loader(demo_dataset, "train", 3, S, 2, seed=1, cache=opened(cache, demo_dataset))))
    plain = {k: v for k, v in batch.items() if not k.startswith("encoder_")}
    torch.manual_seed(0)
    model_a = create_model(stand_in_params(), encoder=StandInEncoder())
    model_b = copy.deepcopy(model_a)
    objective = create_objective(None, device="cpu")
    stats, grads = [], []
    for model, b in ((model_a, batch), (model_b, plain)):
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.AdamW(params, lr=1e-3)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda _: 1.0)
        stats.append(step_mod.train_step(model, b, objective, opt, sched, amp=False))
        grads.append([p.grad for p in params])
    assert stats[0]["loss"] == pytest.approx(stats[1]["loss"], rel=1e-6)
    for ga, gb in zip(*grads, strict=True):
        torch.testing.assert_close(ga, gb, rtol=1e-4, atol=1e-7)


def test_a_run_with_the_cache_logs_what_a_run_without_it_logs(cache, demo_dataset, tmp_path, stand_in):
    schedule = tiny_schedule(steps=6, val_every=3)
    train_mod.train(stand_in_params(), schedule, demo_dataset, tmp_path / "a", progress=False, encoder_cache=cache)
    train_mod.train(stand_in_params(), schedule, demo_dataset, tmp_path / "b", progress=False)
    records = [[json.loads(line) for line in (tmp_path / r / "metrics.jsonl").read_text().splitlines()] for r in "ab"]
    assert len(records[0]) == len(records[1]) == 6  # 3 step records, 3 validations
    for ra, rb in zip(*records):
        for key in ("loss", "psnr", "val_psnr", "val_psnr_masked"):
            if key in ra:
                assert ra[key] == pytest.approx(rb[key], rel=1e-5), (key, ra, rb)
    config = json.loads((tmp_path / "a/config.json").read_text())
    assert config["encoder_cache"] == str(cache.resolve())
    # the cache changes no number, so a run made with it is the same run without it (it resumes, not refused)
    summary = train_mod.train(stand_in_params(), schedule, demo_dataset, tmp_path / "a", progress=False)
    assert summary["steps"] == 6


def _digests(folder):
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*.tar"))}


def test_an_interrupted_encode_resumes_to_the_same_bytes(cache, demo_dataset, tmp_path, monkeypatch):
    out = tmp_path / "c"
    real, calls = cache_mod.sample_members, {"n": 0}

    def interrupted(*args):
        calls["n"] += 1
        if calls["n"] == 6:  # in the second train shard (4 + 2 + ...)
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(cache_mod, "sample_members", interrupted)
    with pytest.raises(Interrupted, match="rerun the same command to resume"):
        encode_mod.encode_dataset(demo_dataset, out, StandInEncoder(), S, "float32", ["train", "val"], "cpu", 3, 0,
                                  progress=False)
    monkeypatch.setattr(cache_mod, "sample_members", real)
    assert list(_digests(out)) == ["train/shard-000000.tar"]  # the finished shard only, no temp file
    assert not (out / "train" / "index.json").exists()
    with pytest.raises(DataError, match="unfinished"):
        opened(out, demo_dataset)
    rows = encode_mod.encode_dataset(demo_dataset, out, StandInEncoder(), S, "float32", ["train", "val"], "cpu", 3,
                                     0, progress=False)
    assert [(r["split"], r["shards"], r["made"], r["encoded"]) for r in rows] == [("train", 4, 3, 8),
                                                                                    ("val", 2, 2, 5)]
    assert _digests(out) == _digests(cache)  # byte for byte the uninterrupted cache
    again = encode_mod.encode_dataset(demo_dataset, out, StandInEncoder(), S, "float32", ["train", "val"], "cpu", 3,
                                      0, progress=False)
    assert [r["made"] for r in again] == [0, 0]
    opened(out, demo_dataset)


def _edited_cache(cache, tmp_path, **fields):
    copy_ = tmp_path / "edited"
    shutil.copytree(cache, copy_)
    info = json.loads((copy_ / "cache.json").read_text())
    for key, value in fields.items():
        if "." in key:
            outer, inner = key.split(".")
            info[outer][inner] = value
        else:
            info[key] = value
    (copy_ / "cache.json").write_text(json.dumps(info))
    return copy_


@pytest.mark.parametrize("fields,match", [
    ({"resolution": 64}, "field 'resolution': the cache's 64, this run's 32"),
    ({"precision": "bf16-autocast"}, "field 'precision'"),
    ({"encoder.name": "psmnet-kitti"}, "field 'encoder'"),
    ({"encoder.weights_sha256": "ab" * 32}, "field 'encoder'"),
    ({"splits.train": "00" * 32}, "field 'splits.train': made from another train/index.json"),
    ({"format": "something/9"}, "field 'format'"),
    ({"precision": "fp8"}, "field 'precision' is 'fp8'"),
    ({"feature_scales": "2,4"}, "field 'feature_scales' missing or not a list"),
])
def test_a_cache_that_does_not_fit_the_run_is_refused_naming_the_field(cache, demo_dataset, tmp_path, fields, match):
    with pytest.raises(DataError, match=match) as e:
        opened(_edited_cache(cache, tmp_path, **fields), demo_dataset)
    assert e.value.flag == "--encoder-cache" and "cache.json" in str(e.value)


def test_a_damaged_cache_is_refused_naming_the_file(cache, demo_dataset, tmp_path):
    damaged = _edited_cache(cache, tmp_path)
    shard = damaged / "train" / "shard-000001.tar"
    shard.write_bytes(shard.read_bytes()[:-1000])  # torn
    with pytest.raises(DataError, match=r"shard-000001.tar: not the size index.json records"):
        opened(damaged, demo_dataset)
    shard.unlink()
    with pytest.raises(DataError, match=r"shard-000001.tar: missing"):
        opened(damaged, demo_dataset)
    (damaged / "cache.json").write_text("{not json")
    with pytest.raises(DataError, match="cache.json: not valid JSON"):
        opened(damaged, demo_dataset)
    with pytest.raises(DataError, match="not an encoder cache"):
        opened(demo_dataset, demo_dataset)


def test_a_sample_whose_arrays_do_not_fit_is_refused_naming_the_member(cache, demo_dataset):
    reader = opened(cache, demo_dataset)
    good = cache_mod.sample_members(torch.ones(1, S, S), [torch.zeros(6, 16, 16), torch.zeros(8, 8, 8)], "float32")
    disparity, features = reader.decode(good, "x:k")
    assert disparity.shape == (1, S, S) and [f.shape for f in features] == [(6, 16, 16), (8, 8, 8)]
    cases = {
        "feature_1.npy: member missing": {k: v for k, v in good.items() if k != "feature_1.npy"},
        r"feature_0.npy: float32 \(6, 8, 8\), cache.json says float32 \(6, 16, 16\)":
            good | cache_mod.sample_members(torch.ones(1, S, S), [torch.zeros(6, 8, 8)], "float32"),
        "feature_0.npy: uint16": good | {"feature_0.npy": cache_mod.sample_members(
            torch.ones(1, S, S), [torch.zeros(6, 16, 16)], "bf16-autocast")["feature_0.npy"]},
        "disparity.npy: non-finite": good | cache_mod.sample_members(torch.full((1, S, S), float("nan")), [],
                                                                        "float32"),
        "disparity.npy: not a .npy array": good | {"disparity.npy": b"garbage"},
    }
    for match, members in cases.items():
        with pytest.raises(DataError, match=match):
            reader.decode(members, "x:k")


def test_bf16_features_are_stored_bit_for_bit():
    f = torch.randn(5, 7, 9).to(torch.bfloat16)
    members = cache_mod.sample_members(torch.zeros(1, 4, 4), [f], "bf16-autocast")
    stored = np.load(io.BytesIO(members["feature_0.npy"]))
    assert stored.dtype == np.uint16
    assert torch.equal(torch.from_numpy(stored).view(torch.bfloat16), f)


def test_cli_encode_then_train_from_the_cache(demo_dataset, tmp_path, capsys):
    out = tmp_path / "cache"
    assert sgmodel_status(["encode", "--data", demo_dataset, "--out", out, "--preset", "cpu-small", "--device", "cpu",
                           "--workers", "0", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "sgmodel train (or ablate) --encoder-cache" in text and "pairs/s" in text
    info = json.loads((out / "cache.json").read_text())
    assert info["encoder"]["name"] == "sgbm" and info["resolution"] == 64 and info["precision"] == "float32"
    run = tmp_path / "run"
    assert sgmodel_status(["train", "--data", demo_dataset, "--out", run, "--preset", "cpu-small", "--steps", "2",
                           "--val-every", "2", "--batch-size", "2", "--device", "cpu", "--no-progress",
                           "--encoder-cache", out]) == 0
    assert "its outputs from" in capsys.readouterr().out
    assert sgmodel_status(["bench", "train", "--data", demo_dataset, "--encoder-cache", out, "--preset", "cpu-small",
                           "--device", "cpu", "--batch-size", "2", "--targets", "2", "--workers", "0", "--warmup", "0",
                           "--repeats", "1"]) == 0
    assert "the encoder outputs read from the cache" in capsys.readouterr().out
    # the cache was made at 64: a run at 32 is refused before it writes anything
    assert sgmodel_status(["train", "--data", demo_dataset, "--out", tmp_path / "run32", "--preset", "cpu-small",
                           "--resolution", "32", "--device", "cpu", "--no-progress", "--encoder-cache", out]) == 2
    assert "field 'resolution'" in capsys.readouterr().err and not (tmp_path / "run32").exists()


@pytest.mark.parametrize("setup,match", [
    ("foreign", "holds files not written by `sgmodel encode` .e.g. 'notes.txt'"),
    ("other", "holds an encoder cache of other settings"),
    ("inside", "inside --data"),
    ("no-data", "does not exist"),
])
def test_cli_encode_refuses_bad_input_and_writes_nothing(demo_dataset, cache, tmp_path, capsys, setup, match):
    out, data = tmp_path / "out", demo_dataset
    if setup == "foreign":
        out.mkdir()
        (out / "notes.txt").write_text("mine")
    elif setup == "other":
        shutil.copytree(cache, out)  # S = 32, the stand-in encoder; the command asks for sgbm at 64
    elif setup == "inside":
        out = demo_dataset / "cache"
    else:
        data = tmp_path / "nothing-here"
    before = sorted(p.name for p in out.rglob("*")) if out.exists() else None
    assert sgmodel_status(["encode", "--data", data, "--out", out, "--preset", "cpu-small", "--device", "cpu",
                           "--workers", "0", "--no-progress"]) == 2
    assert re.search(match, capsys.readouterr().err)
    assert (sorted(p.name for p in out.rglob("*")) if out.exists() else None) == before


def test_bench_train_cache_needs_its_data(tmp_path, capsys):
    assert sgmodel_status(["bench", "train", "--preset", "cpu-small", "--device", "cpu", "--encoder-cache",
                           tmp_path]) == 2
    assert "--encoder-cache: give the --data it caches" in capsys.readouterr().err


def test_ablate_refuses_a_cache_that_does_not_fit_before_writing(demo_dataset, cache, tmp_path, capsys):
    out = tmp_path / "ablation"
    assert sgmodel_status(["ablate", "--data", demo_dataset, "--out", out, "--preset", "cpu-small", "--device", "cpu",
                           "--no-progress", "--encoder-cache", cache]) == 2
    assert "field 'encoder'" in capsys.readouterr().err and not out.exists()


def test_torchrun_two_ranks_write_the_cache_one_process_writes(demo_dataset, tmp_path, capsys):
    """`torchrun --nproc_per_node=2 -m sgmodel.cli encode` on the CPU (gloo): each rank encodes every other
    shard; the cache has the same bytes as one process's, and rank 0 alone prints the summary."""
    import subprocess
    import sys

    flags = ["--data", str(demo_dataset), "--preset", "cpu-small", "--device", "cpu", "--workers", "0",
             "--no-progress", "--batch-size", "3"]
    assert sgmodel_status(["encode", *flags, "--out", tmp_path / "one"]) == 0
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone", "-m", "sgmodel.cli",
           "encode", *flags, "--out", str(tmp_path / "two")]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("2 rank(s); encoder cache in") == 1
    assert _digests(tmp_path / "two") == _digests(tmp_path / "one") and len(_digests(tmp_path / "one")) == 6
    for name in ("cache.json", "train/index.json", "val/index.json"):
        one, two = (json.loads((tmp_path / r / name).read_text()) for r in ("one", "two"))
        one.pop("data", None), two.pop("data", None)
        assert one == two, name
    assert not (tmp_path / "two" / ".lock").exists()
