"""``sgmodel ablate``'s OUT through the one owner (``scenesplat_stereo.common.ownership.check_replaceable``), as every
other command's: new, empty, or an earlier ablation whose every file is unchanged; a killed ablation's OUT (its
manifest still open) resumes; anything else is refused with exit 2, one line naming a file, and every folder as
it was (docs/bad_input.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from scenesplat_stereo.common.ownership import OwnedFolder, write_manifest
from sgmodel.cli import main
from sgmodel.config import PRESETS, ModelParams, TrainParams
from sgmodel.evaluation.ablate import OWNER, check_ablation
from tests.support.bad_input import earlier_output, refused

TINY = ["--preset", "cpu-small", "--resolution", "32", "--padding", "2", "--steps", "2", "--val-every", "2",
        "--device", "cpu", "--no-progress"]


def earlier_ablation(out: Path, closed: bool = True) -> Path:
    """An ablation's OUT: a variant's run and evaluation, a baseline's report, table.md; its manifest closed (the
    ablation ended) or left open (it was killed)."""
    with OwnedFolder(out, OWNER):
        for name in ("shared-default/run/config.json", "shared-default/run/checkpoints/last.pt",
                     "shared-default/eval/metrics.json", "baseline-naive-gs/metrics.json", "table.md"):
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            (out / name).write_text(f"an earlier {name}")
    if not closed:
        write_manifest(out, OWNER, open_=True)
    return out


def ablate_argv(data: Path, out: Path) -> list:
    return ["ablate", "--data", data, "--out", out, *TINY]


def test_ablate_keeps_a_file_the_user_added(demo_dataset, tmp_path, capsys):
    out = earlier_ablation(tmp_path / "ablation")
    (out / "shared-default" / "run" / "notes.txt").write_text("the user's notes on this run")
    refused(main, ablate_argv(demo_dataset, out), capsys,
            "holds files not written by `sgmodel ablate` (e.g. 'shared-default/run/notes.txt')", tmp_path)


def test_ablate_keeps_a_file_changed_since_it_was_written(demo_dataset, tmp_path, capsys):
    out = earlier_ablation(tmp_path / "ablation")
    (out / "table.md").write_text("the user's edited table")
    refused(main, ablate_argv(demo_dataset, out), capsys, "holds 'table.md', changed since `sgmodel ablate` wrote it",
            tmp_path)


def test_ablate_keeps_another_commands_output(demo_dataset, tmp_path, capsys):
    out = earlier_output(tmp_path / "report", "sgmodel eval", ("metrics.json", "table.md"), user_file=None)
    refused(main, ablate_argv(demo_dataset, out), capsys, "holds the output of `sgmodel eval`", tmp_path)


@pytest.mark.parametrize("closed", [True, False], ids=["ended", "killed"])
def test_ablate_resumes_its_own_ablation(demo_dataset, tmp_path, closed):
    """An ablation that ended, or one killed mid-run (its manifest open: the files it added after are its own),
    is OUT's owner's to resume."""
    out = earlier_ablation(tmp_path / "ablation", closed)
    (out / "without-descriptor" / "run").mkdir(parents=True)
    if not closed:  # written by the killed run after it opened its manifest
        (out / "without-descriptor" / "run" / "metrics.jsonl").write_text('{"step": 1}\n')
    base = ModelParams.from_dict(PRESETS["cpu-small"]["model"])
    base.resolution, base.padding = 32, 2
    check_ablation(base, TrainParams(steps=2, val_every=2), demo_dataset, out, None)  # no refusal
