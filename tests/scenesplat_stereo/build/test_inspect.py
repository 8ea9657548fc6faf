"""inspect.py: Table-6 counts, contact sheet, and integrity checks that fail on each kind of damage."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from tests.scenesplat_stereo.build.test_build import settings, write_teachers
from tests.support.shard_edits import rewrite

from scenesplat_stereo.build.inspection import THUMB_WIDTH, inspect_dataset, table
from scenesplat_stereo.build.run import build
from scenesplat_stereo.cli import main
from scenesplat_stereo.shards.encode import decode_image, encode_mask_png


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("inspect")
    build(settings(write_teachers(root / "teachers"), root / "out", samples_per_shard=3))
    return root / "out"


@pytest.fixture
def damaged(dataset, tmp_path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(dataset, out)
    return out


def first_key_only(change):
    state = {"done": False}

    def wrapped(key, members):
        if state["done"]:
            return members
        state["done"] = True
        return change(key, members)

    return wrapped


def test_a_good_dataset_passes_with_table_and_contact_sheet(dataset, tmp_path):
    sheet = tmp_path / "sheet.png"
    report = inspect_dataset(dataset, sheet, sheet_samples=4, progress=False)
    assert report.ok, report.problems
    assert report.samples == 15
    assert report.counts[("ScanNetGS", "train")] | {"psnr": None} == {"scenes": 2, "pairs": 10, "targets": 100, "psnr": None}
    assert report.counts[("ScanNetGS", "val")]["targets"] == 20
    text = table(report)
    assert "| ScanNetGS | train | 2 | 10 | 100 | 37.00 |" in text  # mean of 33, 37, 41 dB over the subset
    assert "| **Total** | val | 1 | 5 | 20 | -- |" in text
    img = decode_image(sheet.read_bytes(), "png")
    # three scenes (one row band each), 2 + 10 thumbnails wide (val scenes have 4 targets: narrower band)
    assert img.shape[1] == 12 * THUMB_WIDTH and img.shape[2] == 3
    assert img.shape[0] == 3 * (18 + 2 * round(THUMB_WIDTH * 24 / 32) + 4)
    # the tier notes: all three teachers use their tier's B and rho
    assert not report.notes
    assert main(["inspect", str(dataset), "--contact-sheet", str(tmp_path / "cli.png"), "--no-progress"]) == 0


@pytest.mark.parametrize("damage, message", [
    (lambda k, m: {n: d for n, d in m.items() if n != "target_03.jpg"}, "missing members"),
    (lambda k, m: m | {"extra.txt": b"x"}, "unexpected members"),
    (lambda k, m: m | {"left.jpg": b"\xff\xd8\xff garbage"}, "does not decode"),
    (lambda k, m: m | {"mask_00.png": encode_mask_png(np.ones((24, 32), bool))[:-20]}, "does not decode"),
    (lambda k, m: m | {"right.jpg": m["mask_00.png"]}, "shape"),
])
def test_member_damage_is_found(damaged, damage, message):
    rewrite(damaged, "train", "shard-000000.tar", first_key_only(damage))
    report = inspect_dataset(damaged, progress=False)
    assert not report.ok
    assert any(message in p for p in report.problems), report.problems


def _edit_json(field, value):
    def change(key, members):
        meta = json.loads(members["json"])
        meta[field] = value(meta)
        return members | {"json": json.dumps(meta).encode()}
    return change


@pytest.mark.parametrize("field, value, message", [
    ("c2w_right", lambda m: (np.array(m["c2w_right"]) + np.outer(np.eye(4)[0], np.eye(4)[3]) * 0.01).tolist(),
     "c2w_right"),  # right camera 1 cm off the baseline
    ("targets", lambda m: m["targets"][::-1], "not c2w_left Trans(rho u_j)"),
    ("c2w_left", lambda m: (np.array(m["c2w_left"]) @ np.diag([1.0, 1.0, -1.0, 1.0])).tolist(),
     "not a rigid"),  # a reflection
    ("frame", lambda m: m["frame"] + 1, "do not match the key"),
    ("baseline", lambda m: m["baseline"] * 2, "c2w_right"),
])
def test_pose_and_field_damage_is_found(damaged, field, value, message):
    rewrite(damaged, "train", "shard-000000.tar", first_key_only(_edit_json(field, value)))
    report = inspect_dataset(damaged, progress=False)
    assert any(message in p for p in report.problems), report.problems


def test_mask_values_other_than_0_and_255_fail(damaged):
    from scenesplat_stereo.shards.encode import encode_png

    grey = encode_png(np.full((24, 32, 1), 128, np.uint8))
    rewrite(damaged, "val", "shard-000000.tar", first_key_only(lambda k, m: m | {"mask_01.png": grey}))
    report = inspect_dataset(damaged, progress=False)
    assert any("mask values" in p for p in report.problems), report.problems


def test_file_level_damage_is_found(damaged, tmp_path):
    (damaged / "train/shard-000001.tar").unlink()
    stats = json.loads((damaged / "stats.json").read_text())
    stats["subsets"]["ScanNetGS"]["splits"]["val"]["pairs"] = 999
    (damaged / "stats.json").write_text(json.dumps(stats))
    with open(damaged / "train/shard-000002.tar", "r+b") as f:
        f.seek(700)
        f.write(b"\x00" * 8)
    report = inspect_dataset(damaged, progress=False)
    problems = "\n".join(report.problems)
    assert "shard-000001.tar: listed in index.json but missing" in problems
    assert "differ from the shards" in problems
    assert "shard-000002.tar: size or sha256" in problems
    assert main(["inspect", str(damaged), "--contact-sheet", str(tmp_path / "x.png"), "--no-progress"]) == 1
    assert not inspect_dataset(tmp_path / "nothing", progress=False).ok
