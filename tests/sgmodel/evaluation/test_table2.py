"""``sgmodel eval`` over several benchmarks and methods: the paper's Table 2 (sgmodel/evaluation/table2.py), on the CPU,
with the StereoNVS fixture import (full-image metrics) and a ReplicaGS-style build (masked metrics)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest

from scenesplat_stereo.shards.benchmark_file import BENCHMARK_NAME
from sgmodel.data.loader import DataError
from sgmodel.evaluation.evaluate import benchmark_flag, summarise, without_valid_pixels
from sgmodel.evaluation.table2 import Column, Row, cell, columns, table_markdown
from tests.support.model_helpers import sgmodel_status


@pytest.fixture(scope="module")
def checkpoint(demo_dataset, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("table2") / "run"
    assert sgmodel_status(["train", "--data", demo_dataset, "--out", run, "--preset", "cpu-small", "--steps", 2, "--val-every", 2,
                "--batch-size", 2, "--resolution", 32, "--padding", 2, "--device", "cpu", "--no-progress"]) == 0
    return run / "checkpoints" / "best.pt"


def test_benchmark_names_and_folders():
    assert benchmark_flag("StereoNVS=data/x") == ("StereoNVS", Path("data/x"))
    assert benchmark_flag("data/replica_gs") == ("replica_gs", Path("data/replica_gs"))
    assert benchmark_flag("A=dir/with=sign") == ("A", Path("dir/with=sign"))
    assert benchmark_flag("=data/y") == ("y", Path("data/y"))


def test_the_table_layout_bold_best_and_missing_lpips():
    cols = [Column("StereoNVS", Path("a"), False, "full image"), Column("ReplicaGS", Path("b"), True, "masks")]
    full = {"psnr": 20.0, "ssim": 0.70, "psnr_masked": 99.0, "ssim_masked": 0.99}
    rows = [Row("forward-splat", "forward-splat", "sgbm", 32, {"StereoNVS": full, "ReplicaGS": full}),
            Row("naive-gs", "naive-GS", "sgbm", 32,
                {"StereoNVS": {"psnr": 21.0, "ssim": 0.60}, "ReplicaGS": {"psnr_masked": 30.0, "ssim_masked": 0.95}}),
            Row("checkpoint", "StereoGaussians", "sgbm", 32,
                {"StereoNVS": {"psnr": 22.5, "ssim": 0.65, "lpips": 0.2},
                 "ReplicaGS": {"psnr_masked": 29.0, "ssim_masked": 0.999, "lpips_masked": 0.1}})]
    text = table_markdown(cols, rows).splitlines()
    assert text[0] == ("| Method | StereoNVS PSNR ↑ | StereoNVS SSIM ↑ | StereoNVS LPIPS ↓ | "
                       "ReplicaGS PSNR ↑ | ReplicaGS SSIM ↑ | ReplicaGS LPIPS ↓ |")
    assert text[2].startswith("| *Stereo geometry without learned prediction* |")
    assert text[3] == "| forward-splat | 20.000 | **0.7000** | n/a | **99.000** | 0.9900 | n/a |"  # masked keys
    assert text[4] == "| naive-GS | 21.000 | 0.6000 | n/a | 30.000 | 0.9500 | n/a |"
    # one LPIPS value per column: nothing to compare it with, so not bold
    assert text[5] == "| **StereoGaussians** | **22.500** | 0.6500 | 0.2000 | 29.000 | **0.9990** | 0.1000 |"
    assert cell({"lpips": 0.3, "lpips_masked": 0.2}, "lpips", True) == 0.2 and cell({}, "lpips", False) is None
    assert cell({"psnr_masked": math.nan}, "psnr", True) is None
    only = table_markdown(cols[:1], rows[2:]).splitlines()
    assert len(only) == 3 and "**22.500**" not in only[2]  # a single row: no group line, nothing bold


def test_means_leave_out_targets_without_a_valid_pixel():
    rows = [{"key": "a", "scene": "s", "target": 0, "psnr": 10.0, "psnr_masked": math.nan},
            {"key": "a", "scene": "s", "target": 1, "psnr": 20.0, "psnr_masked": 30.0}]
    assert summarise(rows) == {"psnr": 15.0, "psnr_masked": 30.0} and without_valid_pixels(rows) == 1
    assert summarise(rows[:1]) == {"psnr": 10.0, "psnr_masked": None}  # undefined: JSON null, never NaN
    assert without_valid_pixels(rows[1:]) == 0


def test_columns_are_checked_before_anything_runs(stereonvs_dataset, replicags_dataset, demo_dataset, tmp_path):
    cols = columns([("StereoNVS", stereonvs_dataset), ("ReplicaGS", replicags_dataset)], "test")
    assert [(c.name, c.masked) for c in cols] == [("StereoNVS", False), ("ReplicaGS", True)]
    assert columns([("demo", demo_dataset)], "val")[0].region == "full image (no benchmark.json)"
    with pytest.raises(ValueError, match="unique"):
        columns([("A", stereonvs_dataset), ("A", replicags_dataset)], "test")
    with pytest.raises(ValueError, match="NAME=PATH"):
        columns([("a.b", stereonvs_dataset)], "test")
    with pytest.raises(DataError, match="split 'test' does not exist"):
        columns([("demo", demo_dataset)], "test")
    broken = tmp_path / "broken"
    shutil.copytree(stereonvs_dataset, broken)
    (broken / BENCHMARK_NAME).write_text('{"masked": "yes"}')
    with pytest.raises(ValueError, match="benchmark.json: field 'masked'"):
        columns([("b", broken)], "test")


def test_table2_for_the_model_and_both_baselines(stereonvs_dataset, replicags_dataset, checkpoint, tmp_path, capsys):
    out = tmp_path / "table"
    assert sgmodel_status(["eval", "--split", "test", "--data", f"StereoNVS={stereonvs_dataset}", "--data",
                f"ReplicaGS={replicags_dataset}", "--checkpoint", checkpoint, "--method", "naive-gs", "--method",
                "forward-splat", "--encoder", "sgbm", "--resolution", 32, "--out", out, "--device", "cpu",
                "--no-progress"]) == 0
    text = (out / "table2.md").read_text()
    assert text in capsys.readouterr().out
    lines = text.splitlines()
    assert [line.split(" | ")[0] for line in lines[3:6]] == ["| forward-splat", "| naive-GS", "| **StereoGaussians**"]
    assert "StereoNVS: " in text and "14 targets; full image" in text
    assert "ReplicaGS: " in text and "120 targets; valid-mask pixels" in text
    assert "LPIPS not computed" in text and lines[5].count("n/a") == 2
    doc = json.loads((out / "table2.json").read_text())
    assert [b["name"] for b in doc["benchmarks"]] == ["StereoNVS", "ReplicaGS"]
    for row in doc["rows"]:
        for bench, masked in (("StereoNVS", False), ("ReplicaGS", True)):
            report = json.loads((out / bench / row["method"] / "metrics.json").read_text())
            key = "_masked" if masked else ""
            assert row["cells"][bench]["psnr"] == report["mean"]["psnr" + key]
            assert row["cells"][bench]["ssim"] == report["mean"]["ssim" + key]
            assert row["cells"][bench]["lpips"] is None
            assert report["targets"] == (14 if bench == "StereoNVS" else 120)
            assert (out / bench / row["method"] / "targets.csv").is_file()
    # the same run alone gives the same numbers
    single = tmp_path / "single"
    assert sgmodel_status(["eval", "--split", "test", "--data", stereonvs_dataset, "--method", "naive-gs", "--encoder", "sgbm",
                "--resolution", 32, "--out", single, "--device", "cpu", "--no-progress"]) == 0
    alone = json.loads((single / "metrics.json").read_text())["mean"]
    assert alone == json.loads((out / "StereoNVS/naive-gs/metrics.json").read_text())["mean"]
    assert not (single / "table2.md").exists()


@pytest.mark.parametrize("argv,message", [
    (["--data", "{tmp}/nowhere", "--method", "naive-gs", "--method", "forward-splat"], "nowhere"),
    (["--data", "{nvs}", "--data", "{nvs}", "--method", "naive-gs"], "unique"),
    (["--data", "{nvs}", "--checkpoint", "{tmp}/nope.pt"], "nope.pt: no such checkpoint"),
    (["--data", "{nvs}", "--data", "X={tmp}/nowhere", "--checkpoint", "{tmp}/none.pt"], "nowhere"),
])
def test_table2_bad_input_exits_2_and_writes_nothing(stereonvs_dataset, tmp_path, capsys, argv, message):
    out = tmp_path / "report"
    code = sgmodel_status(["eval", "--split", "test", "--out", out, "--device", "cpu", "--encoder", "sgbm", "--no-progress"]
               + [a.format(tmp=tmp_path, nvs=stereonvs_dataset) for a in argv])
    assert code == 2 and message in capsys.readouterr().err
    assert not out.exists()
