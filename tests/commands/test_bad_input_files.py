"""Issue 36, single files: a command's single-file output replaces only a file that command wrote.

The benches' ``--out`` reports (``scenesplat-stereo bench render|build|encode|scenes|formats``, ``sgmodel bench
train|predict|encoders``), ``sgmodel pack --out`` and ``irs-pose-recovery recover --out`` (and its ``--work-dir``)
used to overwrite whatever was at their path. Now each asks the one owner
(``scenesplat_stereo.common.ownership.OwnedFile``: ``check_replaceable_file`` before any work, ``write_owned_file``
at the end, a ``.written-by.<name>`` manifest beside the file): a file the command did not write, or one changed
since, is refused at once (exit 2, one line naming the flag and the file, every file as it was); the command's own
earlier output is replaced, atomically. Each refusal is also shown to come before the work: the function the
work starts with is replaced by one that fails the run (exit 1) if it is ever reached.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pipelines import irs_pose_recovery
from scenesplat_stereo.cli import main as toolkit
from scenesplat_stereo.common.ownership import OWNER_FILE, check_replaceable_file
from scenesplat_stereo.shards.encode import encode_png
from sgmodel.cli import main as sgmodel
from tests.support.bad_input import earlier_file, model_checkpoint, refusal, refused, snapshot, tiny_teacher


@dataclass(frozen=True)
class Output:
    """A command's single-file output: the command run small, its owner, the function its work starts with."""

    id: str
    main: Callable
    argv: Callable  # (inputs folder, out, request or None: inputs that are never read may be dummies) -> argv
    owner: str
    work: tuple[str, ...]  # "module:function" that a refused run must not reach
    expect: bytes  # in the file the run writes
    name: str = "report.md"
    rc: int = 0
    stand_in: tuple = ()  # ("module:function", replacement): a slow part stood in for in the rerun test


def bench_formats(inputs: Path, out: Path, request) -> list:
    tiny_teacher(inputs / "teacher")
    (inputs / "none").mkdir()
    return ["bench", "formats", "--captures", inputs / "none", "--streamed", inputs / "none", "--scene",
            inputs / "teacher" / "point_cloud.ply", "--repeats", "1", "--out", out]


def bench_encoders(inputs: Path, out: Path, request) -> list:
    data = request.getfixturevalue("demo_dataset") if request else inputs / "never-read"
    return ["bench", "encoders", "--data", data, "--encoders", "sgbm", "--resolution", "32", "--batch-size", "2",
            "--device", "cpu", "--out", out]


def pack(inputs: Path, out: Path, request) -> list:
    inputs.mkdir()
    return ["pack", model_checkpoint(inputs / "best.pt") if request else inputs / "never-read.pt", "--out", out,
            "--dtype", "bf16"]


def image_folder(folder: Path, n: int = 2) -> Path:
    """``n`` textured 32x24 views of one picture, shifted by 2 px: too small for COLMAP to register, quick."""
    folder.mkdir(parents=True)
    img = (np.random.default_rng(0).random((24, 32 + 2 * n, 3)) * 255).astype(np.uint8)
    for i in range(n):
        (folder / f"{i}.png").write_bytes(encode_png(img[:, 2 * i:2 * i + 32]))
    return folder


def recover(inputs: Path, out: Path, request, *extra) -> list:
    return ["recover", "--images", image_folder(inputs / "images"), "--intrinsics", "30,30,16,12", "--out", out,
            "--threads", "1", *extra]


OUTPUTS = [
    Output("bench render", toolkit, lambda i, o, r: ["bench", "render", "--batch", "--quick", "--device", "cpu",
                                                     "--repeats", "1", "--no-gsplat", "--out", o],
           "scenesplat-stereo bench render", ("scenesplat_stereo.bench.render:batch_table",
                                              "scenesplat_stereo.bench.render:headline"), b"| ours batched |",
           # its deterministic backward takes 8 s on a CPU; tests/scenesplat_stereo/raster/test_raster_batch.py runs it
           stand_in=("scenesplat_stereo.bench.render:batch_table", lambda args, gs: ["| ours batched | (stand-in) |"])),
    Output("bench build", toolkit, lambda i, o, r: [
        "bench", "build", "--gaussians", "2000", "--sh-degree", "0", "--sizes", "32x24", "--pairs", "1",
        "--frames", "2", "--workers", "1", "--batch-pairs", "1", "--qualities", "75", "--device", "cpu",
        "--repeats", "1",
        "--encoder-modes", "threads", "--out", o],
           "scenesplat-stereo bench build", ("scenesplat_stereo.bench.build:synthetic_teacher",), b"| **total** |"),
    Output("bench encode", toolkit, lambda i, o, r: [
        "bench", "encode", "--sizes", "32x24", "--workers", "1", "--modes", "threads", "--repeats", "1", "--samples",
        "1", "--calls", "1", "--targets", "1", "--out", o],
           "scenesplat-stereo bench encode", ("scenesplat_stereo.bench.encode:image_table",),
           b"One image, one call at a time"),
    Output("bench scenes", toolkit, lambda i, o, r: ["bench", "scenes", "--gaussians", "100", "--sh-degrees", "0",
                                                     "--warmup", "0", "--repeats", "1", "--out", o],
           "scenesplat-stereo bench scenes", ("scenesplat_stereo.bench.scenes:writer_rows",), b"Scene writers on"),
    Output("bench formats", toolkit, bench_formats, "scenesplat-stereo bench formats",
           ("scenesplat_stereo.bench.formats:reader_table", "scenesplat_stereo.bench.formats:writer_table"),
           b"Writers (each format written and read back)"),
    Output("sgmodel bench train", sgmodel, lambda i, o, r: [
        "bench", "train", "--device", "cpu", "--encoder", "sgbm", "--resolution", "16", "--padding", "2",
        "--decoder-channels", "8", "--predictor-channels", "8", "--batch-size", "1", "--targets", "1", "--warmup", "0",
        "--repeats", "1", "--no-amp", "--out", o],
           "sgmodel bench train", ("sgmodel.bench.train:create_model",), b"One training step: 16x16"),
    Output("sgmodel bench predict", sgmodel, lambda i, o, r: [
        "bench", "predict", "--preset", "cpu-small", "--device", "cpu", "--size", "48x32", "--warmup", "0",
        "--repeats", "1", "--out", o],
           "sgmodel bench predict", ("sgmodel.bench.predict:bench_model",), b"One pair of 48x32"),
    Output("sgmodel bench encoders", sgmodel, bench_encoders, "sgmodel bench encoders",
           ("sgmodel.bench.encoders:build_encoder",), b"| sgbm |"),
    Output("sgmodel pack", sgmodel, pack, "sgmodel pack", ("sgmodel.train.pack:pack_checkpoint",),
           b"sgmodel-checkpoint-v1", name="model.pt"),
    # two views too small to register: recover writes its poses.json and exits 1 ("no image registers")
    Output("irs-pose-recovery recover", irs_pose_recovery.main, recover, "irs-pose-recovery recover",
           ("pipelines.irs_pose_recovery:recover_poses",), b'"registered": 0', name="poses.json", rc=1),
]


def forbid_the_work(monkeypatch, case: Output) -> None:
    """Make the function ``case``'s work starts with fail the run (exit 1) if it is ever reached."""
    def work_started(*args, **kwargs):
        raise AssertionError(f"{case.id}: the work started before --out was checked")

    for target in case.work:
        module, name = target.split(":")
        monkeypatch.setattr(importlib.import_module(module), name, work_started)


@pytest.mark.parametrize("case", OUTPUTS, ids=[c.id for c in OUTPUTS])
def test_a_users_file_at_the_output_is_kept_and_named_before_any_work(case, tmp_path, capsys, monkeypatch):
    forbid_the_work(monkeypatch, case)
    out = tmp_path / "reports" / case.name
    out.parent.mkdir()
    out.write_bytes(b"the user's own file")
    argv = case.argv(tmp_path / "in", out, None)
    refused(case.main, argv, capsys, f"error: --out {out}: exists and was not written by `{case.owner}` (no "
            f"{OWNER_FILE}.{case.name} beside it), and `{case.owner}` replaces only what it wrote; choose another "
            f"--out, or move the file away", tmp_path)


@pytest.mark.parametrize("case", OUTPUTS, ids=[c.id for c in OUTPUTS])
def test_a_rerun_replaces_its_own_earlier_output(case, tmp_path, capsys, request, monkeypatch):
    if case.stand_in:
        module, name = case.stand_in[0].split(":")
        monkeypatch.setattr(importlib.import_module(module), name, case.stand_in[1])
    out = earlier_file(tmp_path / "reports" / case.name, case.owner)
    rc, err = refusal(case.main, case.argv(tmp_path / "in", out, request), capsys)
    assert rc == case.rc, err
    assert case.expect in out.read_bytes()
    assert sorted(p.name for p in out.parent.iterdir()) == [f"{OWNER_FILE}.{case.name}", case.name]  # no temp file
    assert check_replaceable_file(out, "--out", case.owner) == out  # the new file is recorded as its own


# ------------------------------------------------------------------ the cases of one command each, beyond the two


def test_a_report_changed_since_the_bench_wrote_it_is_kept(tmp_path, capsys, monkeypatch):
    case = next(c for c in OUTPUTS if c.id == "sgmodel bench train")
    forbid_the_work(monkeypatch, case)
    out = earlier_file(tmp_path / "report.md", case.owner)
    out.write_text("an earlier report, with the user's notes\n")
    refused(sgmodel, case.argv(tmp_path, out, None), capsys,
            f"--out {out}: exists and changed since `sgmodel bench train` wrote it", tmp_path)


def test_a_report_of_another_bench_is_kept(tmp_path, capsys, monkeypatch):
    case = next(c for c in OUTPUTS if c.id == "sgmodel bench predict")
    forbid_the_work(monkeypatch, case)
    out = earlier_file(tmp_path / "report.md", "sgmodel bench train")
    refused(sgmodel, case.argv(tmp_path, out, None), capsys,
            f"--out {out}: exists and is the output of `sgmodel bench train`", tmp_path)


def test_pack_replaces_its_own_model_file_and_refuses_its_own_checkpoint(tmp_path, capsys):
    from sgmodel.model.checkpoint import load_checkpoint

    ckpt = model_checkpoint(tmp_path / "best.pt")
    out = tmp_path / "shared" / "model.pt"  # a new folder is made
    assert sgmodel(["pack", str(ckpt), "--out", str(out), "--dtype", "fp32"]) == 0
    fp32 = out.stat().st_size
    assert sgmodel(["pack", str(ckpt), "--out", str(out), "--dtype", "bf16"]) == 0  # its own file: replaced
    assert out.stat().st_size < 0.7 * fp32 and load_checkpoint(out)["step"] == 2
    assert str(out) in capsys.readouterr().out
    refused(sgmodel, ["pack", ckpt, "--out", ckpt], capsys, f"--out {ckpt}: inside CHECKPOINT {ckpt}", tmp_path)
    (tmp_path / "folder.pt").mkdir()
    refused(sgmodel, ["pack", ckpt, "--out", tmp_path / "folder.pt"], capsys, "folder.pt: is a folder", tmp_path)


def test_recover_keeps_a_users_colmap_project_at_work_dir(tmp_path, capsys, monkeypatch):
    forbid_the_work(monkeypatch, next(c for c in OUTPUTS if c.id == "irs-pose-recovery recover"))
    project = tmp_path / "project"
    (project / "sparse" / "0").mkdir(parents=True)
    (project / "database.db").write_bytes(b"the user's COLMAP database")  # recover removes its own database first
    (project / "sparse" / "0" / "cameras.bin").write_bytes(b"the user's model")
    refused(irs_pose_recovery.main, recover(tmp_path / "in", tmp_path / "poses.json", None, "--work-dir", project),
            capsys, f"--work-dir {project}: holds files not written by `irs-pose-recovery recover` (e.g. "
                    f"'database.db')", tmp_path)
    assert not (tmp_path / "poses.json").exists()


def test_recover_reruns_in_its_own_work_dir(tmp_path, capsys):
    work, out = tmp_path / "work", tmp_path / "poses.json"
    argv = recover(tmp_path / "in", out, None, "--work-dir", work)
    assert refusal(irs_pose_recovery.main, argv, capsys)[0] == 1  # nothing registers in two tiny views
    assert (work / "database.db").is_file() and (work / "images" / "000000.png").is_symlink()  # COLMAP's staged links
    before = snapshot(work)
    assert refusal(irs_pose_recovery.main, argv, capsys)[0] == 1  # the links are recorded as its own: no refusal
    assert snapshot(work).keys() == before.keys() and (work / "images" / "000001.png").is_symlink()
    (work / "notes.txt").write_text("the user's")
    refused(irs_pose_recovery.main, argv, capsys, "holds files not written by `irs-pose-recovery recover` (e.g. "
                                                  "'notes.txt')", tmp_path)


@pytest.mark.parametrize("argv, message", [
    (["bench", "build", "--encoder-modes", "threads,warp"], "--encoder-modes from"),
    (["bench", "build", "--jpeg-encoders", "gif"], "--jpeg-encoders from"),
    (["bench", "build", "--repeats", "0"], "--repeats >= 1"),
    (["bench", "encode", "--modes", "warp"], "bad --modes ['warp']"),
    (["bench", "encode", "--workers", "0"], "--workers below 1"),
], ids=["build-mode", "build-jpeg", "build-repeats", "encode-mode", "encode-workers"])
def test_a_bench_refuses_a_bad_flag_in_one_line_with_exit_2(argv, message, tmp_path, capsys):
    """The benches' own flag checks are refusals like argparse's (exit 2, one line), not exit 1; nothing written."""
    refused(toolkit, [*argv, "--out", tmp_path / "report.md"], capsys, message, tmp_path)
    assert not (tmp_path / "report.md").exists()
