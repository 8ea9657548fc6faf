"""Issue 36, classes 1 and 2: outputs never replace what they did not write, and stay apart from the inputs.

Every command that writes a folder asks one owner (``scenesplat_stereo.common.ownership.check_replaceable``) whether it
may: the folder is new, empty, or every file in it is one the command wrote (its manifest, ``.written-by``, lists
each file with its size and sha256), unchanged. Each test gives a command an output folder it must not write (a
user's file added to an earlier output, a file changed since, another tool's dataset, an output inside an input
or holding one) and asserts the exit status, the one-line message, and that every folder involved is byte for
byte as it was (docs/bad_input.md lists the cases).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipelines import irs_pose_recovery, irs_targets
from scenesplat_stereo.cli import main as toolkit
from scenesplat_stereo.common import ownership
from scenesplat_stereo.common.ownership import OWNER_FILE, OwnedFolder, StagedFolder, check_replaceable, write_manifest
from scenesplat_stereo.shards.encode import encode_png
from sgmodel.cli import main as sgmodel
from tests.support.bad_input import earlier_output, refusal, refused, tiny_teacher


class caplog_warnings:
    """``with caplog_warnings() as lines:`` the messages of the warnings logged meanwhile (any logger)."""

    def __enter__(self) -> list[str]:
        import logging

        self.lines: list[str] = []
        self.handler = logging.Handler(logging.WARNING)
        self.handler.emit = lambda record: self.lines.append(record.getMessage())
        logging.getLogger().addHandler(self.handler)
        return self.lines

    def __exit__(self, *exc) -> None:
        import logging

        logging.getLogger().removeHandler(self.handler)


@pytest.fixture
def pair(tmp_path) -> Path:
    """A 48x32 textured stereo pair and a FoundationStereo K.txt."""
    rng = np.random.default_rng(0)
    img = (rng.random((32, 52, 3)) * 255).astype(np.uint8)
    (tmp_path / "l.png").write_bytes(encode_png(img[:, 2:50]))
    (tmp_path / "r.png").write_bytes(encode_png(img[:, 4:52]))
    (tmp_path / "K.txt").write_text("50 0 24 0 50 16 0 0 1\n0.1\n")
    return tmp_path


def predict_argv(pair: Path, out: Path, *extra) -> list:
    return ["predict", "--left", pair / "l.png", "--right", pair / "r.png", "--calib", pair / "K.txt", "--out", out,
            "--method", "naive-gs", "--encoder", "sgbm", "--device", "cpu", *extra]


# ------------------------------------------------------------------------------ 1. only what the command wrote
def test_predict_keeps_a_file_the_user_added_to_an_earlier_prediction(pair, capsys):
    out = earlier_output(pair / "out", "sgmodel predict")
    refused(sgmodel, predict_argv(pair, out), capsys, "holds files not written by `sgmodel predict` (e.g. 'notes.txt')",
            pair)


def test_predict_keeps_a_file_changed_since_it_was_written(pair, capsys):
    out = earlier_output(pair / "out", "sgmodel predict", user_file=None)
    (out / "scene.ply").write_text("the user's edit")
    refused(sgmodel, predict_argv(pair, out), capsys, "holds 'scene.ply', changed since `sgmodel predict` wrote it",
            pair)


def test_predict_keeps_an_output_of_an_earlier_version_without_a_file_list(pair, capsys):
    out = pair / "out"
    out.mkdir()
    (out / "scene.ply").write_text("old")
    (out / OWNER_FILE).write_text("sgmodel predict\n")  # the marker of the earlier version: no file list
    refused(sgmodel, predict_argv(pair, out), capsys, "an earlier version of `sgmodel predict`, which kept no list",
            pair)


def test_predict_keeps_another_commands_output(pair, capsys):
    out = earlier_output(pair / "out", "sgmodel rectify", ("left.png",), user_file=None)
    refused(sgmodel, predict_argv(pair, out), capsys, "holds the output of `sgmodel rectify`", pair)


def test_eval_keeps_a_file_the_user_added_to_an_earlier_report(demo_dataset, tmp_path, capsys):
    out = earlier_output(tmp_path / "report", "sgmodel eval", ("metrics.json",))
    refused(sgmodel, ["eval", "--data", demo_dataset, "--out", out, "--method", "naive-gs", "--encoder", "sgbm",
                      "--device", "cpu", "--no-progress"], capsys,
            "holds files not written by `sgmodel eval` (e.g. 'notes.txt')", tmp_path, demo_dataset)


def test_eval_table_keeps_a_file_the_user_added(demo_dataset, tmp_path, capsys):
    out = tmp_path / "tables"
    out.mkdir()
    (out / "notes.md").write_text("the user's notes")
    refused(sgmodel, ["eval", "--data", f"a={demo_dataset}", "--data", f"b={demo_dataset}", "--out", out, "--method",
                      "naive-gs", "--encoder", "sgbm", "--device", "cpu", "--no-progress"], capsys,
            "holds files not written by `sgmodel eval` (e.g. 'notes.md')", tmp_path, demo_dataset)


def test_rectify_keeps_a_file_the_user_added(pair, capsys):
    out = earlier_output(pair / "rect", "sgmodel rectify", ("left.png", "right.png"))
    refused(sgmodel, ["rectify", "--left", pair / "l.png", "--right", pair / "r.png", "--rig", pair / "K.txt",
                      "--out", out], capsys, "holds files not written by `sgmodel rectify` (e.g. 'notes.txt')", pair)


def test_encode_keeps_another_tools_dataset(demo_dataset, tmp_path, capsys):
    out = tmp_path / "cache"
    (out / "train").mkdir(parents=True)
    (out / "train" / "shard-000000.tar").write_bytes(b"another tool's shard")
    refused(sgmodel, ["encode", "--data", demo_dataset, "--out", out, "--encoder", "sgbm", "--device", "cpu",
                      "--no-progress"], capsys, "holds files not written by `sgmodel encode` (e.g. "
            "'train/shard-000000.tar')", tmp_path)


def test_train_keeps_a_folder_that_is_not_a_run(demo_dataset, tmp_path, capsys):
    out = earlier_output(tmp_path / "pred", "sgmodel predict")
    refused(sgmodel, ["train", "--data", demo_dataset, "--out", out, "--preset", "cpu-small", "--device", "cpu",
                      "--no-progress"], capsys, "holds the output of `sgmodel predict`", tmp_path)


def test_import_stereonvs_keeps_a_file_the_user_added(stereonvs_scenes, tmp_path, capsys):
    root = stereonvs_scenes[0].folder.parent
    out = earlier_output(tmp_path / "out", "scenesplat-stereo import stereonvs", ("test/shard-000000.tar",),
                         user_file="test/my_pairs.tar")
    refused(toolkit, ["import", "stereonvs", root, "--out", out, "--baseline", "0.12", "--no-progress"], capsys,
            "holds files not written by `scenesplat-stereo import stereonvs` (e.g. 'test/my_pairs.tar')", tmp_path,
            root)


def test_build_keeps_another_tools_dataset(tmp_path, capsys):
    teachers = tiny_teacher(tmp_path / "teachers" / "room")
    out = tmp_path / "irs"
    (out / "train").mkdir(parents=True)
    (out / "train" / "shard-000000.tar").write_bytes(b"an IRS shard")
    refused(toolkit, ["build", "--teachers", teachers.parent, "--out", out, "--device", "cpu", "--no-progress"],
            capsys, "holds files not written by `scenesplat-stereo build` (e.g. 'train/shard-000000.tar')", tmp_path)


def test_render_keeps_a_file_the_user_added(tmp_path, capsys):
    teacher = tiny_teacher(tmp_path / "room")
    out = earlier_output(tmp_path / "frames", "scenesplat-stereo render", ("frame_0000.png",))
    refused(toolkit, ["render", teacher, "--out", out, "--device", "cpu"], capsys,
            "holds files not written by `scenesplat-stereo render` (e.g. 'notes.txt')", tmp_path)


def test_demo_teachers_keep_the_users_own_room(tmp_path, capsys):
    (tmp_path / "teachers" / "demo_room_01").mkdir(parents=True)
    (tmp_path / "teachers" / "demo_room_01" / "point_cloud.ply").write_text("the user's scan")
    refused(toolkit, ["demo-teachers", tmp_path / "teachers", "--scenes", "2", "--gaussians", "2000", "--no-progress"],
            capsys, "demo_room_01: holds files not written by `scenesplat-stereo demo-teachers` (e.g. "
            "'point_cloud.ply')", tmp_path)
    assert not (tmp_path / "teachers" / "demo_room_00").exists()  # checked before the first room is written


def test_demo_teachers_too_few_gaussians_name_the_flag(tmp_path, capsys):
    refused(toolkit, ["demo-teachers", tmp_path / "teachers", "--gaussians", "200"], capsys,
            "--gaussians 200: must be >= 2000", tmp_path)
    assert not (tmp_path / "teachers").exists()


def test_demo_teachers_replace_their_own_rooms_and_nothing_else(tmp_path, capsys):
    teachers = tmp_path / "teachers"
    (teachers / "my_scan").mkdir(parents=True)
    (teachers / "my_scan" / "point_cloud.ply").write_text("the user's scan")
    argv = ["demo-teachers", teachers, "--scenes", "1", "--gaussians", "2000", "--frames", "2", "--no-progress"]
    assert toolkit([str(a) for a in argv]) == 0
    first = (teachers / "demo_room_00" / "scene.json").read_bytes()
    assert toolkit([str(a) for a in argv]) == 0  # its own room: replaced
    assert (teachers / "demo_room_00" / "scene.json").read_bytes() == first
    assert (teachers / "my_scan" / "point_cloud.ply").read_text() == "the user's scan"
    assert sorted(p.name for p in teachers.iterdir()) == ["demo_room_00", "my_scan"]  # no staging folder left
    capsys.readouterr()


def test_irs_targets_keep_another_tools_shards(tmp_path, capsys):
    from tests.commands.test_bad_input_irs import poses_dir

    poses = poses_dir(tmp_path)
    out = tmp_path / "shards"
    (out / "train").mkdir(parents=True)
    (out / "train" / "shard-000000.tar").write_bytes(b"a build's shard")
    refused(irs_targets.main, [poses, "--out", out, "--no-progress"], capsys,
            "holds files not written by `irs-targets` (e.g. 'train/shard-000000.tar')", tmp_path)


def irs_root(tmp_path: Path) -> Path:
    """An IRS-like root: one variant folder with one left image (what finds the variant)."""
    (tmp_path / "irs" / "v0").mkdir(parents=True)
    (tmp_path / "irs" / "v0" / "l_0.png").write_bytes(encode_png(np.zeros((6, 8, 3), np.uint8)))
    return tmp_path / "irs"


def test_irs_pose_recovery_keeps_a_file_the_user_added(tmp_path, capsys):
    irs_root(tmp_path)
    out = earlier_output(tmp_path / "poses", "irs-pose-recovery", ("v0/report.json",))
    refused(irs_pose_recovery.main, [tmp_path / "irs", "--out", out, "--no-progress"], capsys,
            "holds files not written by `irs-pose-recovery` (e.g. 'notes.txt')", tmp_path)


def test_irs_pose_recovery_with_nothing_to_do_says_so(tmp_path, capsys):
    (tmp_path / "irs" / "empty").mkdir(parents=True)
    refused(irs_pose_recovery.main, [tmp_path / "irs", "--out", tmp_path / "poses", "--no-progress"], capsys,
            "no IRS variant (no folder holding l_<n>.png images)", tmp_path)
    assert not (tmp_path / "poses").exists()


# ------------------------------------------------------------------------------ 2. outputs apart from inputs
def test_import_stereonvs_never_writes_into_the_benchmark(stereonvs_scenes, capsys):
    root = stereonvs_scenes[0].folder.parent
    out = root / "lab" / "images" / "left"
    refused(toolkit, ["import", "stereonvs", root, "--out", out, "--baseline", "0.12", "--no-progress"], capsys,
            f"--out {out}: inside ROOT {root}", root)


def test_rectify_out_holding_its_own_input(pair, capsys):
    out = earlier_output(pair / "rect", "sgmodel rectify", ("left.png", "right.png"), user_file=None)
    refused(sgmodel, ["rectify", "--left", out / "left.png", "--right", out / "right.png", "--rig", pair / "K.txt",
                      "--out", out], capsys, "holds --left", pair)


def test_predict_out_holding_its_own_input(pair, capsys):
    out = earlier_output(pair / "rect", "sgmodel predict", ("depth.png",), user_file=None)
    shutil.copy(pair / "l.png", out / "l.png")
    write_manifest(out, "sgmodel predict")  # as if predict had written l.png: ownership passes, apartness refuses
    refused(sgmodel, predict_argv(pair, out)[:1] + ["--left", out / "l.png"] + predict_argv(pair, out)[3:], capsys,
            "holds --left", pair)


def test_render_out_inside_the_teacher(tmp_path, capsys):
    teacher = tiny_teacher(tmp_path / "room")
    refused(toolkit, ["render", teacher, "--out", teacher / "renders", "--device", "cpu"], capsys,
            "inside SOURCE", tmp_path)


def test_build_out_inside_the_teachers(tmp_path, capsys):
    teacher = tiny_teacher(tmp_path / "teachers" / "room")
    refused(toolkit, ["build", "--teachers", teacher.parent, "--out", teacher.parent / "dataset", "--device", "cpu",
                      "--no-progress"], capsys, "inside --teachers", tmp_path)


def test_irs_targets_out_inside_the_poses(tmp_path, capsys):
    from tests.commands.test_bad_input_irs import poses_dir

    poses = poses_dir(tmp_path)
    refused(irs_targets.main, [poses, "--out", poses / "shards", "--no-progress"], capsys, "inside POSES_DIR",
            tmp_path)


def test_irs_pose_recovery_out_inside_the_dataset(tmp_path, capsys):
    irs_root(tmp_path)
    refused(irs_pose_recovery.main, [tmp_path / "irs", "--out", tmp_path / "irs" / "poses", "--no-progress"], capsys,
            "inside ROOT", tmp_path)


def test_irs_recover_out_inside_the_images(tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    for i in range(2):
        (images / f"{i}.png").write_bytes(encode_png(np.full((8, 8, 3), 40 * i, np.uint8)))
    refused(irs_pose_recovery.main, ["recover", "--images", images, "--intrinsics", "8,8,4,4", "--out",
                                     images / "poses.json"], capsys, "inside --images", tmp_path)


# ------------------------------------------------------------------------------ 5. flags that do not apply
@pytest.mark.parametrize("flags,message", [
    (["--codec", "ffv1"], "--codec: for a video"),
    (["--trajectory", "orbit:0.2"], "--trajectory: for a video"),
    (["--batch-size", "8"], "--batch-size: for a video"),
    (["--frames", "--max-frames", "3"], "--frames, --max-frames: for a video"),
])
def test_predict_refuses_video_flags_for_a_still_pair(pair, capsys, flags, message):
    refused(sgmodel, predict_argv(pair, pair / "out", *flags), capsys, message, pair)
    assert not (pair / "out").exists()


def test_predict_refuses_a_scene_format_for_a_video_without_scenes(pair, capsys):
    refused(sgmodel, ["predict", "--video", pair / "sbs.mp4", "--calib", pair / "K.txt", "--out", pair / "out",
                      "--method", "naive-gs", "--format", "spz"], capsys,
            "--format spz: a video writes scene files only with --frames", pair)


# ------------------------------------------------------------------------------ 3. one plausibility check
@pytest.mark.parametrize("baseline,word", [("120", "long"), ("0.0005", "short")])
def test_predict_baseline_flag_in_another_unit_is_named(pair, capsys, baseline, word):
    """--baseline in millimetres (120) or a typo (0.0005): one warning naming the flag and its unit (a warning, not a
    refusal: a 3 m rig exists)."""
    from sgmodel.pairs.calib import calib_from_flags

    with caplog_warnings() as lines:
        calib_from_flags("50,50,24,16", baseline)
    assert lines == [f"--baseline: a baseline of {float(baseline):.4g} m is {word} for a stereo rig "
                     f"({'up to 2 m is usual' if word == 'long' else '3 mm or more is usual'}): --baseline is in "
                     f"metres (120 mm is --baseline 0.12)"]


def test_calib_files_check_their_baseline_in_their_unit(tmp_path):
    from sgmodel.pairs.calib import read_calib

    (tmp_path / "K.txt").write_text("50 0 24 0 50 16 0 0 1\n120\n")  # millimetres in FoundationStereo's metres
    (tmp_path / "calib.txt").write_text("cam0=[50 0 24; 0 50 16; 0 0 1]\nbaseline=0.193\n")  # metres, not mm
    with caplog_warnings() as lines:
        assert read_calib(tmp_path / "K.txt").baseline == 120.0
        assert read_calib(tmp_path / "calib.txt").baseline == pytest.approx(0.000193)
    assert "line 2 (baseline): a baseline of 120 m is long" in lines[0] and "line 2 is in metres" in lines[0]
    assert "baseline=0.193" not in lines[1] and "is short" in lines[1] and "baseline= is in millimetres" in lines[1]


def test_import_stereonvs_baseline_in_millimetres_is_named(stereonvs_scenes, tmp_path, capsys):
    root = stereonvs_scenes[0].folder.parent
    rc, err = refusal(toolkit, ["import", "stereonvs", root, "--out", tmp_path / "o", "--baseline", "120",
                                "--scenes", "nope"], capsys)
    assert rc == 2 and "warning: --baseline 120: a baseline of 120 m is long" in err
    assert "--baseline is in metres" in err and not (tmp_path / "o").exists()


def test_build_baseline_in_millimetres_is_named(tmp_path, capsys):
    rc, err = refusal(toolkit, ["build", "--teachers", tmp_path / "none", "--out", tmp_path / "o", "--baseline",
                                "100", "--device", "cpu"], capsys)
    assert rc == 2 and "warning: --baseline 100: a baseline of 100 m is long for a stereo rig" in err, err
    assert "--baseline is in the teachers' world units" in err and not (tmp_path / "o").exists()


def test_a_pair_of_ros_camera_info_files_is_named_as_such(pair, capsys):
    for side in ("left", "right"):
        (pair / f"{side}.yaml").write_text(
            "image_width: 48\nimage_height: 32\ncamera_name: " + side + "\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
            "  data: [50, 0, 24, 0, 50, 16, 0, 0, 1]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n"
            "  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\nprojection_matrix:\n  rows: 3\n  cols: 4\n"
            "  data: [50, 0, 24, 0, 0, 50, 16, 0, 0, 0, 1, 0]\n")
    refused(sgmodel, ["rectify", "--left", pair / "l.png", "--right", pair / "r.png", "--rig", pair / "left.yaml",
                      pair / "right.yaml", "--out", pair / "rect"], capsys,
            "right.yaml are ROS camera_info files (one camera each, from camera_calibration): they hold no stereo "
            "extrinsics", pair)


def fake_matches(dy: float, dx: float, n: int = 60):
    """Matched points (left, right) with vertical disparity ``dy`` varying across the image and disparity ``dx``."""
    rng = np.random.default_rng(1)
    p1 = rng.uniform(0, 100, (n, 2))
    p2 = p1 + np.stack([-dx * np.ones(n), dy * (p1[:, 0] / 50 - 1)], axis=1)
    return p1, p2


@pytest.mark.parametrize("rectified_here,dy,expected", [
    (True, 8.0, "the calibration that rectified them does not fit these images"),
    (False, 8.0, "the pair is not rectified is the likelier cause than swapped images"),
    (False, 0.0, "the left and right images are probably swapped"),
], ids=["rectified here", "not rectified", "swapped"])
def test_negative_disparity_with_vertical_disparity_is_not_called_swapped(monkeypatch, rectified_here, dy, expected):
    from sgmodel.pairs import stereo_check

    monkeypatch.setattr(stereo_check, "matches", lambda *a, **k: fake_matches(dy, -5.0))
    check = stereo_check.measure(None, None, rectified_here=rectified_here)
    assert expected in check.warnings[-1], check.warnings
    assert ("swapped (--left" in check.warnings[-1]) == (dy == 0.0)


# ------------------------------------------------------------------------------ 4. degenerate input
@pytest.mark.parametrize("data", ["bench=", ""])
def test_eval_data_without_a_path_is_not_the_current_folder(tmp_path, capsys, data):
    refused(sgmodel, ["eval", "--data", data, "--out", tmp_path / "report", "--method", "naive-gs"], capsys,
            f"--data {data!r}: no PATH (give [NAME=]PATH)", tmp_path)


# ------------------------------------------------------------------------------ 4. our bug is not bad input
def in_our_package(tmp_path: Path, source: str):
    """A function whose code lives in a module of ours (``sgmodel.fake``, source in a real file for linecache)."""
    path = tmp_path / "fake.py"
    path.write_text(source)
    namespace = {"__name__": "sgmodel.fake"}
    exec(compile(source, str(path), "exec"), namespace)
    return namespace["f"]


@pytest.mark.parametrize("source,code,message", [
    ("def f():\n    a, b = [1, 2, 3]\n", 1, "internal error: ValueError: too many values to unpack"),
    ("def f():\n    return int('x1')\n", 1, "internal error: ValueError: invalid literal for int()"),
    ("def f():\n    raise ValueError(\n        '--n 3: must be < 2')\n", 2, "error: --n 3: must be < 2"),
], ids=["implicit unpacking", "implicit int()", "raise statement"])
def test_a_value_error_of_our_own_bug_is_internal_and_a_refusal_is_bad_input(tmp_path, capsys, source, code,
                                                                            message):
    from scenesplat_stereo.common.commandline import Parser, run_command

    parser = Parser(prog="tool")
    parser.set_defaults(func=lambda args: in_our_package(tmp_path, source)())
    rc = run_command(parser, [])
    err = capsys.readouterr().err
    assert rc == code and message in err and len(err.splitlines()) == 1, err


# ------------------------------------------------------------------------------ the owner itself
def test_a_symlinked_output_is_written_through(tmp_path):
    real = earlier_output(tmp_path / "real", "tool do", user_file=None)
    (tmp_path / "link").symlink_to(real)
    assert check_replaceable(tmp_path / "link", "--out", "tool do") == real.resolve()
    with StagedFolder(tmp_path / "link", "tool do") as tmp:
        (tmp / "depth.png").write_text("new")
    assert (tmp_path / "link").is_symlink() and sorted(p.name for p in real.iterdir()) == [OWNER_FILE, "depth.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "real"]  # nothing hidden left behind


def test_an_earlier_output_moved_aside_by_a_killed_run_is_put_back(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    aside = tmp_path / f".tmp-out.pid{int(dead.stdout)}.abc.old"  # killed between its two renames
    earlier_output(aside, "tool do", user_file=None)
    (tmp_path / f".tmp-out.pid{int(dead.stdout)}.abc").mkdir()  # and its half-written new content
    with pytest.raises(RuntimeError):
        with StagedFolder(tmp_path / "out", "tool do"):
            raise RuntimeError("this run fails too")
    assert (tmp_path / "out" / "scene.ply").read_text() == "an earlier scene.ply"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_killed_in_place_writer_resumes_and_no_one_else_takes_over(tmp_path):
    out = tmp_path / "out"
    with OwnedFolder(out, "tool do"):
        (out / "part-0").write_text("done")
        os.replace(out / OWNER_FILE, tmp_path / "open-manifest")  # what a SIGKILL now would leave
        shutil.copy(tmp_path / "open-manifest", out / OWNER_FILE)
        (out / "part-1").write_text("half")
        break_off = json.loads((out / OWNER_FILE).read_text())
        assert break_off["open"] is True
        check_replaceable(out, "--out", "tool do")  # its rerun resumes
        with pytest.raises(ValueError, match="holds the output of `tool do`"):
            check_replaceable(out, "--out", "other tool")
    assert json.loads((out / OWNER_FILE).read_text())["files"].keys() == {"part-0", "part-1"}
    assert "open" not in json.loads((out / OWNER_FILE).read_text())


def test_large_files_are_remembered_by_size_and_time(tmp_path, monkeypatch):
    monkeypatch.setattr(ownership, "HASH_LIMIT", 4)
    out = earlier_output(tmp_path / "out", "tool do", user_file=None)
    assert set(json.loads((out / OWNER_FILE).read_text())["files"]["scene.ply"]) == {"size", "mtime_ns"}
    check_replaceable(out, "--out", "tool do")
    os.utime(out / "scene.ply", ns=(1, 1))
    with pytest.raises(ValueError, match="changed since `tool do` wrote it"):
        check_replaceable(out, "--out", "tool do")


# ------------------------------------------------------------------------------ 7. the first run as a newcomer
def test_warp_says_nothing_about_a_missing_cuda_driver():
    """Every command imports the rasteriser; on a CPU machine Warp's native notice must not greet the user."""
    run = subprocess.run([sys.executable, "-c", "import scenesplat_stereo.raster._warp as w; import warp as wp; "
                          "print(wp.get_device('cpu'))"], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    assert run.returncode == 0 and run.stdout.strip() == "cpu", run.stderr
    assert "Could not find or load the NVIDIA CUDA driver" not in run.stderr, run.stderr


# ------------------------------------------------------------------------------ 6. Ctrl-C
CTRL_C_IN_A_POOL = """
import os, signal, sys, time
from concurrent.futures import ProcessPoolExecutor
import multiprocessing
from scenesplat_stereo.common.commandline import Parser, quiet_worker_interrupts, run_command

def work(_):
    return 1

def command(args):
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"),
                             initializer=quiet_worker_interrupts) as pool:
        [pool.submit(work, i).result() for i in range(2)]  # the workers now wait for work (where Ctrl-C hurts)
        time.sleep(1)
        os.killpg(0, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole process group
        time.sleep(20)

if __name__ == "__main__":
    os.setpgrp()
    p = Parser(prog="tool")
    p.set_defaults(func=command)
    sys.exit(run_command(p, []))
"""


def test_ctrl_c_ends_a_command_with_pool_workers_in_one_line(tmp_path):
    (tmp_path / "ctrl_c.py").write_text(CTRL_C_IN_A_POOL)
    run = subprocess.run([sys.executable, str(tmp_path / "ctrl_c.py")], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    assert run.returncode == 130 and run.stderr.strip() == "tool: interrupted", run.stderr
