"""Ctrl-C, then the same command again (issue 36, class 6), for the long commands: ``scenesplat-stereo build``,
``sgmodel eval`` (a table of reports), ``sgmodel predict --video`` and ``sgmodel encode`` (``sgmodel train``'s case is
``tests/sgmodel/train/test_train_runs.py``).

Each command runs as a real process in a process group of its own; once it has made progress (a first shard, a
first report, a first frame's scene) the whole group gets SIGINT, as a terminal's Ctrl-C sends it to the command
and its worker processes. It must end with exit 130 and one line saying what was kept and to rerun (no
traceback, from it or a worker), leave no file half-written under its final name, and the same command run
again must finish (resuming where there is something to resume) with the bytes of a run never stopped
(docs/bad_input.md).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from scenesplat_stereo.cli import main as toolkit
from scenesplat_stereo.common.ownership import OWNER_FILE
from scenesplat_stereo.shards import webdataset as shards
from sgmodel.cli import main as sgmodel
from tests.support.bad_input import snapshot
from tests.support.paths import REPO

ATTEMPTS = 3  # a command that finished before the signal reached it (a loaded machine) is run again, afresh


def ctrl_c(argv: list, made_progress: Callable[[], bool], timeout: float = 300) -> tuple[int, str]:
    """Run ``python -m argv`` in a new process group, wait until ``made_progress()``, send SIGINT to the whole
    group; (exit status, stderr). The status is 0 when the command ended before the signal was sent."""
    proc = subprocess.Popen([sys.executable, "-m", *map(str, argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=REPO, start_new_session=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    end = time.monotonic() + timeout
    while not made_progress() and proc.poll() is None:
        assert time.monotonic() < end, f"no progress within {timeout} s: {argv}"
        time.sleep(0.01)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=timeout)
    return proc.returncode, err


def interrupted(root: Path, make: Callable[[Path], tuple[list, Callable[[], bool]]]) -> tuple[Path, str]:
    """``ctrl_c`` of the command ``make(out)`` gives for a fresh output folder ``root/out<attempt>``, at most
    ``ATTEMPTS`` times while the command finishes first; the interrupted attempt's folder, and its stderr's one
    line (warnings left out)."""
    for attempt in range(ATTEMPTS):
        out = root / f"out{attempt}"
        rc, err = ctrl_c(*make(out))
        if rc != 0:
            break
    lines = [line for line in err.splitlines() if ": warning: " not in line and not line.startswith("Warp ")]
    assert rc == 130 and len(lines) == 1 and "Traceback" not in err, (rc, err)
    return out, lines[0]


def temp_files(root: Path) -> list[str]:
    """Files and folders of unfinished writes (``.tmp-*``) under ``root`` and beside it."""
    return sorted(str(p) for p in [*root.parent.glob(".tmp-*"), *root.rglob(".tmp-*")])


def finished_shards_only(root: Path, split: str) -> None:
    """Every ``shard-*.tar`` under its final name in ``root/split`` is finished: its done marker lists it with
    its size and sha256, and it reads to its end."""
    done = {info["shard"]: info for info in shards.finished_shards(root, split).values()}
    names = sorted(p.name for p in (root / split).glob("shard-*.tar"))
    assert names and names == sorted(done), (names, sorted(done))
    for name in names:
        assert (root / split / name).stat().st_size == done[name]["bytes"], name
        assert [k for k, _ in shards.iter_shard(root / split / name)] == done[name]["keys"], name


# ------------------------------------------------------------------------------------------------------ build


@pytest.fixture(scope="module")
def long_teachers(tmp_path_factory) -> Path:
    """Two demo rooms of 20 frames: 40 training pairs, 20 shards of 2."""
    from scenesplat_stereo.build.demo import write_demo_teachers

    root = tmp_path_factory.mktemp("teachers20")
    write_demo_teachers(root, n_scenes=2, n_frames=20, width=96, height=72, num_gaussians=2000, progress=False)
    return root


def test_ctrl_c_of_build_then_the_rerun_resumes_to_the_same_bytes(long_teachers, tmp_path, capsys):
    flags = ["--teachers", long_teachers, "--samples-per-shard", "2", "--workers", "1", "--val-scenes", "0",
             "--batch-pairs", "1", "--no-progress"]

    def make(out):
        return (["scenesplat_stereo.cli", "build", "--out", out, *flags],
                lambda: any((out / "train" / shards.DONE_DIR).glob("shard-*.json")))

    out, line = interrupted(tmp_path, make)
    kept = len(shards.finished_shards(out, "train"))
    assert 1 <= kept < 20 and line == (f"scenesplat-stereo build: interrupted: {kept} of 20 shards of {out} are "
                                       f"finished and kept (each whole); rerun the same command to resume")
    finished_shards_only(out, "train")
    assert not (out / "train" / "index.json").exists()
    argv = ["build", "--out", out, *flags]
    assert toolkit([str(a) for a in argv]) == 0
    assert f"kept from an earlier run: {kept} shards" in capsys.readouterr().out
    assert toolkit([str(a) for a in ["build", "--out", tmp_path / "whole", *flags]]) == 0
    assert not temp_files(out) and snapshot(out) == snapshot(tmp_path / "whole")


# ------------------------------------------------------------------------------------------------------- eval


def test_ctrl_c_of_an_eval_table_keeps_its_finished_reports_and_the_rerun_completes(demo_dataset, tmp_path):
    flags = ["--data", f"a={demo_dataset}", "--data", f"b={demo_dataset}", "--data", f"c={demo_dataset}",
             "--method", "naive-gs", "--encoder", "sgbm", "--resolution", "64", "--batch-size", "1", "--device",
             "cpu", "--no-progress"]

    def make(out):
        return ["sgmodel.cli", "eval", "--out", out, *flags], lambda: (out / "a" / "naive-gs" / "metrics.json").exists()

    out, line = interrupted(tmp_path, make)
    reports = sorted(str(p.parent.relative_to(out)) for p in out.glob("*/*/metrics.json"))
    assert reports[:1] == ["a/naive-gs"] and len(reports) < 3
    assert line == (f"sgmodel eval: interrupted: {len(reports)} of 3 reports finished and kept in {out} "
                    f"({', '.join(reports)}), the table not written; rerun the same command")
    assert not temp_files(out) and not (out / "table2.md").exists()
    for report in reports:  # each whole: its four files and a closed manifest
        assert sorted(p.name for p in (out / report).iterdir()) == sorted(
            [OWNER_FILE, "metrics.json", "scenes.md", "sheet.png", "targets.csv"])
    assert "open" not in json.loads((out / OWNER_FILE).read_text())  # OUT's manifest closed: the rerun may go on
    assert sgmodel([str(a) for a in ["eval", "--out", out, *flags]]) == 0
    assert sgmodel([str(a) for a in ["eval", "--out", tmp_path / "whole", *flags]]) == 0
    assert not temp_files(out) and snapshot(out) == snapshot(tmp_path / "whole")


# ---------------------------------------------------------------------------------------------- predict --video


@pytest.fixture(scope="module")
def clip24(tmp_path_factory) -> Path:
    """A 24-frame stereo clip of a demo room (96x64, lossless FFV1) and its K.txt."""
    from scripts.figures.video_demo import render_clip

    folder = tmp_path_factory.mktemp("clip24")
    render_clip(folder, 24, 96, 64, num_gaussians=6000)
    return folder


def test_ctrl_c_of_predict_video_leaves_out_as_it_was_and_the_rerun_completes(clip24, tmp_path):
    flags = ["--left-video", clip24 / "left.mkv", "--right-video", clip24 / "right.mkv", "--calib", clip24 / "K.txt",
             "--frames", "--format", "ply", "--codec", "ffv1", "--batch-size", "1", "--method", "naive-gs",
             "--encoder", "sgbm", "--resolution", "64", "--device", "cpu", "--no-progress"]
    earlier = tmp_path / "earlier.txt"  # a file beside OUT: nothing but OUT may change

    def make(out):
        return (["sgmodel.cli", "predict", "--out", out, *flags],
                lambda: any(tmp_path.glob(f".tmp-{out.name}.pid*/frames/000001.ply")))

    earlier.write_text("the user's")
    out, line = interrupted(tmp_path, make)
    assert line == (f"sgmodel predict: interrupted: --out {out} is as it was (a prediction replaces it only when "
                    f"complete); rerun the same command")
    assert not out.exists() and not temp_files(out) and earlier.read_text() == "the user's"
    assert sgmodel([str(a) for a in ["predict", "--out", out, *flags]]) == 0
    assert sgmodel([str(a) for a in ["predict", "--out", tmp_path / "whole", *flags]]) == 0
    from scripts.figures.video_demo import read_frames

    video = "novel_view.mkv"  # its container holds a date and a random id: its frames are compared
    got, want = snapshot(out), snapshot(tmp_path / "whole")
    assert len([name for name in got if name.startswith("frames/")]) == 24 and not temp_files(out)
    assert {k: v for k, v in got.items() if k not in (video, OWNER_FILE)} == \
        {k: v for k, v in want.items() if k not in (video, OWNER_FILE)}
    frames = read_frames(out / video)
    assert frames.shape[0] == 24 and (frames == read_frames(tmp_path / "whole" / video)).all()


# ------------------------------------------------------------------------------------------------------ encode


def test_ctrl_c_of_encode_then_the_rerun_resumes_to_the_same_bytes(demo_dataset, tmp_path, capsys):
    flags = ["--data", demo_dataset, "--preset", "cpu-small", "--resolution", "64", "--batch-size", "1", "--workers",
             "1", "--device", "cpu", "--no-progress"]

    def make(out):
        # a shard is finished once its done marker is written, after its .tar is in place (as build's test waits)
        return (["sgmodel.cli", "encode", "--out", out, *flags],
                lambda: any((out / "train" / shards.DONE_DIR).glob("shard-*.json")))

    out, line = interrupted(tmp_path, make)
    kept = len(shards.finished_shards(out, "train"))
    assert 1 <= kept < 4 and line == (f"sgmodel encode: interrupted: {kept} of 4 train shards written this run; "
                                      f"rerun the same command to resume")
    finished_shards_only(out, "train")
    assert not (out / "train" / "index.json").exists() and not (out / "val").exists()
    assert sgmodel([str(a) for a in ["encode", "--out", out, *flags]]) == 0
    assert [line.split()[:3] for line in capsys.readouterr().out.splitlines()[2:4]] == [
        ["train", "4", str(4 - kept)], ["val", "2", "2"]]  # split, shards, made now: the finished ones kept
    assert sgmodel([str(a) for a in ["encode", "--out", tmp_path / "whole", *flags]]) == 0
    assert not temp_files(out) and snapshot(out) == snapshot(tmp_path / "whole")
