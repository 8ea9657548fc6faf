"""Bad input to the IRS pipelines (python -m pipelines.irs_pose_recovery / irs_targets): exit 2 with the flag
or file+field named, and an earlier run's shards never removed before every input is checked."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipelines import irs, irs_pose_recovery, irs_targets
from tests.support.bad_input import run_cli, snapshot


@pytest.fixture
def earlier(tmp_path) -> Path:
    out = tmp_path / "shards"
    (out / "train" / ".done").mkdir(parents=True)
    (out / "train" / "shard-000000.tar").write_bytes(b"earlier shard")
    (out / "train" / ".done" / "shard-000000.json").write_text("{}")
    return out


def poses_dir(tmp_path: Path, name: str = "v0", drop: str | None = None) -> Path:
    d = tmp_path / "poses" / name
    d.mkdir(parents=True)
    (d / "report.json").write_text(json.dumps({"kept": True}))
    frame = {"frame": 0, "left": "l_0.png", "right": "r_0.png", "disparity": "d_0.exr",
             "c2w_left": np.eye(4).tolist(), "c2w_right": np.eye(4).tolist()}
    poses = {"source": str(tmp_path), "frames": [frame], "K": np.eye(3).tolist(), "width": 8, "height": 6,
             "baseline": 0.1}
    if drop in poses:
        poses.pop(drop)
    elif drop:
        frame.pop(drop)
    (d / "poses.json").write_text(json.dumps(poses))
    return d.parent


TARGET_FLAGS = [
    (["--depth-stride", "0"], "--depth-stride 0: must be >= 1"),
    (["--depth-stride", "-3"], "--depth-stride -3: must be >= 1"),
    (["--samples-per-shard", "0"], "--samples-per-shard 0: must be >= 1"),
    (["--workers", "0"], "--workers 0: must be >= 1"),
    (["--focal-baseline", "0"], "--focal-baseline 0.0: must be > 0"),
    (["--min-targets", "x"], "--min-targets 'x': expected a whole number"),
]


@pytest.mark.parametrize("flags,message", TARGET_FLAGS, ids=[" ".join(c[0]) for c in TARGET_FLAGS])
def test_targets_flags(tmp_path, earlier, capsys, flags, message):
    before = snapshot(earlier)
    rc, text = run_cli(irs_targets.main, [str(poses_dir(tmp_path)), "--out", str(earlier), "--no-progress", *flags],
                       capsys)
    assert rc == 2 and message in text, text
    assert snapshot(earlier) == before


@pytest.mark.parametrize("drop,message", [("K", "poses.json: missing field(s) K"),
                                          ("source", "missing field(s) source"),
                                          ("c2w_left", "frames[0]: missing field(s) c2w_left")])
def test_poses_json_missing_a_key(tmp_path, earlier, capsys, drop, message):
    before = snapshot(earlier)
    rc, text = run_cli(irs_targets.main, [str(poses_dir(tmp_path, drop=drop)), "--out", str(earlier),
                                          "--no-progress", "--val-variants", "0"], capsys)
    assert rc == 2 and message in text, text
    assert snapshot(earlier) == before


@pytest.mark.parametrize("name", ["v.1", "my variant", "a__b"])
def test_variant_name_unusable_in_keys_is_refused_before_removal(tmp_path, earlier, capsys, name):
    before = snapshot(earlier)
    rc, text = run_cli(irs_targets.main, [str(poses_dir(tmp_path, name)), "--out", str(earlier), "--no-progress",
                                          "--val-variants", "0"], capsys)
    assert rc == 2 and "is not usable in sample keys" in text, text
    assert snapshot(earlier) == before


def test_targets_out_is_a_file(tmp_path, capsys):
    out = tmp_path / "file"
    out.write_text("x")
    rc, text = run_cli(irs_targets.main, [str(poses_dir(tmp_path)), "--out", str(out), "--no-progress",
                                          "--val-variants", "0"], capsys)
    assert rc == 2 and "--out" in text and "not a folder" in text and out.read_text() == "x"


RECOVERY_FLAGS = [
    (["--image-size", "0x0"], "--image-size '0x0': width and height must be >= 1"),
    (["--image-size", "960by540"], "--image-size '960by540': expected WIDTHxHEIGHT"),
    (["--workers", "0"], "--workers 0: must be >= 1"),
    (["--max-scale-iqr", "-1"], "--max-scale-iqr -1.0: must be > 0"),
]


@pytest.mark.parametrize("flags,message", RECOVERY_FLAGS, ids=[" ".join(c[0]) for c in RECOVERY_FLAGS])
def test_recovery_flags(tmp_path, earlier, capsys, flags, message):
    before = snapshot(earlier)
    rc, text = run_cli(irs_pose_recovery.main, [str(tmp_path), "--out", str(earlier), "--no-progress", *flags], capsys)
    assert rc == 2 and message in text, text
    assert snapshot(earlier) == before


def test_recover_without_images(tmp_path, capsys):
    rc, text = run_cli(irs_pose_recovery.main, ["recover", "--images", str(tmp_path), "--intrinsics", "1,1,1,1",
                                                "--out", str(tmp_path / "p.json")], capsys)
    assert rc == 2 and "--images" in text and "no images" in text and not (tmp_path / "p.json").exists()


def test_variant_names_are_key_safe(tmp_path):
    (tmp_path / "Room 1" / "v.2").mkdir(parents=True)
    assert irs.variant_name(tmp_path, tmp_path / "Room 1" / "v.2") == "Room_1-v_2"
