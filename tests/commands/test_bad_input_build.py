"""Bad input to ``scenesplat-stereo build`` and ``render``: exit 2, one message naming the flag or file,
and nothing in OUT written or removed (docs/bad_input.md lists the cases)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from scenesplat_stereo.cli import main
from scenesplat_stereo.common.ownership import StagedFolder
from tests.support.bad_input import run_cli, snapshot, tiny_teacher


@pytest.fixture(scope="module")
def teachers(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("teachers")
    tiny_teacher(root / "room_a")
    tiny_teacher(root / "room_b")
    return root


@pytest.fixture
def out(tmp_path) -> Path:
    """An OUT from an 'earlier run': a build.json of other settings and a file that must survive."""
    out = tmp_path / "out"
    (out / "train").mkdir(parents=True)
    (out / "train" / "keep.txt").write_text("earlier output")
    (out / "build.json").write_text("{}\n")  # an earlier build's (whose rules decide what it may replace)
    return out


BUILD_CASES = [  # (extra flags, part of the message)
    (["--targets", "11"], "--targets 11: must be in 1..10"),
    (["--targets", "0"], "--targets 0: must be >= 1"),
    (["--val-scenes", "5"], "--val-scenes"),
    (["--orbit", "radius=1,elevation=95"], "elevation must be in (-90, 90)"),
    (["--orbit", "radius=0"], "radius must be a finite number > 0"),
    (["--orbit", "radius=1,size=0x4"], "width and height must be >= 1"),
    (["--baseline", "0"], "--baseline 0.0: must be > 0"),
    (["--baseline", "-0.1"], "--baseline -0.1: must be > 0"),
    (["--rho", "0"], "--rho 0.0: must be > 0"),
    (["--rho", "nan"], "--rho 'nan': expected a finite number"),
    (["--max-frames", "0"], "--max-frames 0: must be >= 1"),
    (["--device", "foo"], "--device 'foo': expected cpu, cuda or cuda:<n>"),
    (["--device", "mps"], "the rasteriser runs on cpu or cuda only"),
    (["--resolution", "0x10"], "--resolution '0x10': width and height must be >= 1"),
    (["--resolution", "640"], "--resolution '640': expected WIDTHxHEIGHT"),
    (["--samples-per-shard", "0"], "--samples-per-shard 0: must be >= 1"),
    (["--batch-pairs", "0"], "--batch-pairs 0: must be >= 1"),
    (["--workers", "-1"], "--workers -1: must be >= 0"),
    (["--effects", "blur"], "unknown effect(s) ['blur']"),
    (["--min-psnr", "high"], "--min-psnr 'high': expected a number"),
    (["--val-scenes", "DemoGS=x"], "--val-scenes 'DemoGS=x'"),
    (["--min-psnr", "99"], "no teacher to build from"),
    (["--jpeg-encoder", "nvjpeg", "--device", "cpu"], "--jpeg-encoder nvjpeg: needs a CUDA --device, got cpu"),
    (["--jpeg-encoder", "gpu"], "invalid choice: 'gpu'"),
]


@pytest.mark.parametrize("flags,message", BUILD_CASES, ids=[" ".join(c[0]) for c in BUILD_CASES])
def test_build_refuses_before_writing(teachers, out, capsys, flags, message):
    before = snapshot(out)
    rc, text = run_cli(main, ["build", "--teachers", str(teachers), "--out", str(out), "--no-progress",
                              "--device", "cpu", "--val-scenes", "1", *flags], capsys)
    assert rc == 2 and message in text, text
    assert snapshot(out) == before  # no build.json recorded, nothing removed


def test_build_missing_teachers_root(tmp_path, out, capsys):
    before = snapshot(out)
    rc, text = run_cli(main, ["build", "--teachers", str(tmp_path / "nowhere"), "--out", str(out),
                              "--device", "cpu"], capsys)
    assert rc == 2 and "nowhere is not a folder" in text and snapshot(out) == before


def test_build_out_is_a_file(teachers, tmp_path, capsys):
    out = tmp_path / "out.txt"
    out.write_text("not a folder")
    rc, text = run_cli(main, ["build", "--teachers", str(teachers), "--out", str(out), "--device", "cpu"], capsys)
    assert rc == 2 and "--out" in text and "not a folder" in text and out.read_text() == "not a folder"


def test_build_unreadable_build_json(teachers, out, capsys):
    (out / "build.json").write_text("{broken")
    before = snapshot(out)
    rc, text = run_cli(main, ["build", "--teachers", str(teachers), "--out", str(out), "--device", "cpu",
                              "--val-scenes", "1"], capsys)
    assert rc == 2 and "build.json: unreadable" in text and snapshot(out) == before


def test_refused_build_then_corrected_build_is_accepted(teachers, tmp_path, capsys):
    """The issue's first case: a refused --targets 11 must not record settings that refuse the fix."""
    out = tmp_path / "out"
    common = ["build", "--teachers", str(teachers), "--out", str(out), "--no-progress", "--device", "cpu",
              "--val-scenes", "1", "--max-frames", "1", "--workers", "0"]
    assert run_cli(main, common + ["--targets", "11"], capsys)[0] == 2
    assert not (out / "build.json").exists()
    rc, text = run_cli(main, common + ["--targets", "2"], capsys)
    assert rc == 0, text
    assert json.loads((out / "build.json").read_text())["trainval"]["targets"] == 2


@pytest.fixture
def frames(tmp_path) -> Path:
    """An earlier render's OUT (its manifest says so): a refused render must leave it as it was."""
    with StagedFolder(tmp_path / "frames", "scenesplat-stereo render") as tmp:
        (tmp / "frame_0000.png").write_bytes(b"an earlier frame")
    return tmp_path / "frames"


RENDER_CASES = [
    (["--resolution", "0x0"], "--resolution '0x0': width and height must be >= 1"),
    (["--batch", "0"], "--batch 0: must be >= 1"),
    (["--max-frames", "-2"], "--max-frames -2: must be >= 1"),
    (["--orbit", "radius=-3"], "radius must be a finite number > 0"),
    (["--device", "foo"], "--device 'foo'"),
]


@pytest.mark.parametrize("flags,message", RENDER_CASES, ids=[" ".join(c[0]) for c in RENDER_CASES])
def test_render_flags(teachers, frames, capsys, flags, message):
    before = snapshot(frames)
    rc, text = run_cli(main, ["render", str(teachers / "room_a"), "--out", str(frames), *flags], capsys)
    assert rc == 2 and message in text, text
    assert snapshot(frames) == before


def test_render_missing_source(tmp_path, frames, capsys):
    before = snapshot(frames)
    rc, text = run_cli(main, ["render", str(tmp_path / "none.ply"), "--out", str(frames), "--device", "cpu"], capsys)
    assert rc == 2 and "SOURCE" in text and "no such file" in text and snapshot(frames) == before


def test_render_garbage_ply(tmp_path, frames, capsys):
    ply = tmp_path / "junk.ply"
    ply.write_bytes(b"not a ply at all")
    before = snapshot(frames)
    rc, text = run_cli(main, ["render", str(ply), "--out", str(frames), "--device", "cpu"], capsys)
    assert rc == 2 and "not a PLY file" in text and snapshot(frames) == before
