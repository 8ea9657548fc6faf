"""``sgmodel eval`` and ``sgmodel ablate`` on the demo dataset: the report's files, agreement with the
training loop's own validation, the baselines, the Table 4 layout, and bad input."""

from __future__ import annotations

import csv
import json

import pytest

from scenesplat_stereo.common.ownership import OWNER_FILE
from sgmodel.cli import main as sgmodel_main
from sgmodel.config import DecoderParams, ModelParams, PredictorParams, TrainParams
from sgmodel.evaluation import evaluate as evaluate_mod
from sgmodel.evaluation.ablate import ablate, variants
from sgmodel.train import loop as train_mod
from tests.support.bad_input import snapshot


def tiny() -> tuple[ModelParams, TrainParams]:
    p = ModelParams(resolution=32, padding=2, decoder=DecoderParams(channels=16, groups=4),
                    predictor=PredictorParams(channels=16, groups=4))
    p.encoder.name = "sgbm"
    return p, TrainParams(steps=2, batch_size=2, targets=2, val_every=2, workers=0, amp=False, sheet_samples=1)


def cli(args: list[str]) -> int:
    try:
        return sgmodel_main([str(a) for a in args])
    except SystemExit as e:
        return e.code


@pytest.fixture(scope="module")
def trained(demo_dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("eval") / "run"
    params, schedule = tiny()
    train_mod.train(params, schedule, demo_dataset, run, progress=False)
    return run


def test_eval_of_a_checkpoint_matches_the_training_validation(demo_dataset, trained, tmp_path):
    out = tmp_path / "report"
    assert cli(["eval", "--data", demo_dataset, "--checkpoint", trained / "checkpoints/best.pt", "--out", out,
                "--device", "cpu", "--no-progress"]) == 0
    result = json.loads((out / "metrics.json").read_text())
    logged = [json.loads(line) for line in (trained / "metrics.jsonl").read_text().splitlines()]
    best = max((r for r in logged if "val_psnr" in r and r["step"] > 0), key=lambda r: r["val_psnr"])
    assert result["targets"] == best["val_targets"] == 20  # 5 validation pairs x 4 stored targets
    assert result["mean"]["psnr"] == pytest.approx(best["val_psnr"], abs=1e-4)
    assert result["mean"]["psnr_masked"] == pytest.approx(best["val_psnr_masked"], abs=1e-4)
    assert result["encoder"] == "sgbm" and "not computed" in result["lpips"]
    rows = list(csv.DictReader((out / "targets.csv").open()))
    assert len(rows) == 20 and {r["target"] for r in rows} == {"0", "1", "2", "3"}
    assert "| all | 20 |" in (out / "scenes.md").read_text()
    assert (out / "sheet.png").stat().st_size > 0


@pytest.mark.parametrize("method", ["naive-gs", "forward-splat"])
def test_eval_of_the_baselines(demo_dataset, tmp_path, method):
    out = tmp_path / method
    assert cli(["eval", "--data", demo_dataset, "--method", method, "--encoder", "sgbm", "--resolution", 32,
                "--out", out, "--device", "cpu", "--no-progress"]) == 0
    mean = json.loads((out / "metrics.json").read_text())["mean"]
    assert 5 < mean["psnr"] < 60 and 0 < mean["ssim"] <= 1


def test_ctrl_c_while_a_report_is_written_leaves_the_earlier_one_as_it_was(demo_dataset, tmp_path, capsys,
                                                                          monkeypatch):
    out = tmp_path / "report"
    argv = ["eval", "--data", demo_dataset, "--method", "naive-gs", "--encoder", "sgbm", "--resolution", 32, "--out",
            out, "--device", "cpu", "--no-progress"]
    assert cli(argv) == 0
    before = snapshot(tmp_path)
    capsys.readouterr()

    def interrupt(kept):  # Ctrl-C while the new report's files are written into its staging folder
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate_mod, "target_sheet", interrupt)
    assert cli(argv) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"sgmodel eval: interrupted: --out {out} is as it was (a report replaces it only when complete); rerun the "
        f"same command")
    assert snapshot(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == ["report"]


@pytest.mark.parametrize("argv,message", [
    (["--checkpoint", "{tmp}/none.pt"], "no such checkpoint"),
    (["--method", "naive-gs", "--encoder", "nope"], "nope"),
    (["--method", "naive-gs", "--split", "test"], "test"),
])
def test_eval_bad_input_exits_2_and_writes_nothing(demo_dataset, tmp_path, capsys, argv, message):
    out = tmp_path / "report"
    code = cli(["eval", "--data", demo_dataset, "--out", out, "--device", "cpu", "--no-progress"]
               + [a.format(tmp=tmp_path) for a in argv])
    assert code == 2 and message in capsys.readouterr().err
    assert not out.exists()


def test_ablate_writes_the_table_4_layout_and_resumes(demo_dataset, tmp_path):
    params, schedule = tiny()
    names = [name for _, name, _ in variants(params)]
    assert names[0] == "Shared default" and len(names) == 10 and names[-3:] == ["without padding", "4 pixels", "8 pixels"]  # 0, 2P, 4P
    text = ablate(params, schedule, demo_dataset, tmp_path, "cpu", None, only=["default", "RGB-D"], progress=False)
    assert "| **Shared default** |" in text and "| **(A) Input conditioning** |" in text
    assert "| Without RGB-D conditioning | n/a |" in text  # sgbm has no features: not applicable
    assert "| naive-gs |" in text and "| forward-splat |" in text
    assert (tmp_path / "table.md").read_text() == text
    manifest = json.loads((tmp_path / OWNER_FILE).read_text())  # every file recorded as the ablation's
    assert manifest["owner"] == "sgmodel ablate" and "open" not in manifest
    assert {"table.md", "shared-default/eval/metrics.json", "shared-default/run/checkpoints/best.pt"} <= \
        set(manifest["files"])
    before = (tmp_path / "shared-default/eval/metrics.json").stat().st_mtime_ns
    ablate(params, schedule, demo_dataset, tmp_path, "cpu", None, only=["default"], progress=False)
    assert (tmp_path / "shared-default/eval/metrics.json").stat().st_mtime_ns == before  # read back, not redone
