"""Data whose valid masks are empty (issue 36, class 4: degenerate data never reaches library code).

A target whose mask has no valid pixel has no masked metric (NaN per target): ``sgmodel eval`` and training's
validation leave it out of the masked means and count it, so one such sample never makes a mean NaN; the
training loss (full images) does not see masks at all. A split in which no target has a valid pixel is refused
before anything is written (``sgmodel.data.loader.check_valid_pixels``): exit 2, one line naming the split and
its shards, every folder as it was (docs/bad_input.md)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from sgmodel.cli import main
from tests.support.bad_input import refused
from tests.support.shard_edits import without_valid_pixels

TINY = ["--preset", "cpu-small", "--resolution", "32", "--padding", "2", "--steps", "2", "--val-every", "2",
        "--device", "cpu", "--no-progress"]
BASELINE = ["--method", "naive-gs", "--encoder", "sgbm", "--resolution", "32", "--device", "cpu", "--no-progress"]


@pytest.fixture(scope="module")
def empty(demo_dataset, tmp_path_factory) -> dict[str, Path]:
    """Copies of the demo dataset: no valid pixel anywhere ("all"), none in the validation split ("val"), and
    none in the first validation sample ("one", its 4 targets)."""
    root = tmp_path_factory.mktemp("empty_masks")
    first = json.loads((demo_dataset / "val" / "index.json").read_text())["shards"][0]["keys"][0]
    return {"all": without_valid_pixels(demo_dataset, root / "all"),
            "val": without_valid_pixels(demo_dataset, root / "val", splits=("val",)),
            "one": without_valid_pixels(demo_dataset, root / "one", splits=("val",), keys={first})}


def strict_json(path: Path):
    """The JSON document in ``path``, refusing NaN and infinities (which JSON does not have)."""
    def no_constant(name):
        raise AssertionError(f"{path}: {name} is not JSON")
    return json.loads(path.read_text(), parse_constant=no_constant)


@pytest.mark.parametrize("command,data,split,shards", [
    ("eval", "all", "val", "shard-000000.tar to shard-000001.tar"),
    ("train", "all", "train", "shard-000000.tar to shard-000003.tar"),
    ("train", "val", "val", "shard-000000.tar to shard-000001.tar"),
    ("ablate", "val", "val", "shard-000000.tar to shard-000001.tar"),
], ids=["eval-all-empty", "train-all-empty", "train-val-empty", "ablate-val-empty"])
def test_a_split_without_a_valid_pixel_is_refused_before_writing(empty, tmp_path, capsys, command, data, split,
                                                                 shards):
    out = tmp_path / "out"
    flags = BASELINE if command == "eval" else TINY
    refused(main, [command, "--data", empty[data], "--out", out, *flags], capsys,
            f"--data {empty[data] / split}: no target has a valid pixel (every mask_<jj>.png in {shards} is empty)",
            empty[data])
    assert not out.exists()


def test_eval_leaves_out_and_counts_the_targets_without_a_valid_pixel(demo_dataset, empty, tmp_path, capsys):
    assert main(["eval", "--data", demo_dataset, "--out", tmp_path / "whole", *BASELINE]) == 0
    capsys.readouterr()
    assert main(["eval", "--data", empty["one"], "--out", tmp_path / "one", *BASELINE]) == 0
    assert "20 targets (4 without a valid pixel, left out of the masked means)" in capsys.readouterr().out
    result = strict_json(tmp_path / "one" / "metrics.json")
    assert result["targets"] == 20 and result["targets_without_valid_pixels"] == 4
    with open(tmp_path / "whole" / "targets.csv") as f:  # the untouched data's per-target values
        whole = list(csv.DictReader(f))
    emptied = json.loads((demo_dataset / "val" / "index.json").read_text())["shards"][0]["keys"][0]
    kept = [r for r in whole if r["key"] != emptied]
    assert len(kept) == 16
    for name in ("psnr_masked", "ssim_masked"):
        assert result["mean"][name] == pytest.approx(sum(float(r[name]) for r in kept) / 16, rel=1e-9), name
    assert result["mean"]["psnr"] == pytest.approx(strict_json(tmp_path / "whole" / "metrics.json")["mean"]["psnr"])


def test_training_does_not_see_masks_and_its_validation_counts_the_empty_ones(demo_dataset, empty, tmp_path):
    for name, data in (("whole", demo_dataset), ("one", empty["one"])):
        assert main(["train", "--data", data, "--out", tmp_path / name, *TINY, "--log-every", "1"]) == 0
    records = {name: [json.loads(line) for line in (tmp_path / name / "metrics.jsonl").read_text().splitlines()]
               for name in ("whole", "one")}
    losses = {name: [r["loss"] for r in rs if "loss" in r] for name, rs in records.items()}
    assert len(losses["one"]) == 2 and losses["one"] == losses["whole"]  # the same steps, bit for bit
    vals = [r for r in records["one"] if "val_psnr" in r]
    assert [r["val_targets_without_valid_pixels"] for r in vals] == [4, 4]
    assert all(math.isfinite(r["val_psnr_masked"]) for r in vals)
    weights = torch.load(tmp_path / "one" / "checkpoints" / "last.pt", weights_only=True)["model"]
    assert all(torch.isfinite(v).all() for v in weights.values() if v.is_floating_point())
