"""``inspect``: a missing OUT exits 2; broken index/stats files are named problems (exit 1, no traceback);
IRS samples are checked by what their JSON says (real target frames), not as Fibonacci targets."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scenesplat_stereo.build.inspection import inspect_dataset
from scenesplat_stereo.build.protocol import SamplePlan
from scenesplat_stereo.cli import main
from scenesplat_stereo.scene.cameras import right_camera
from scenesplat_stereo.shards import webdataset as shards
from scenesplat_stereo.shards.encode import SampleImages, decode_image, encode_sample
from scenesplat_stereo.shards.sample import SampleMeta
from tests.support.bad_input import run_cli, snapshot


def irs_dataset(out, far: bool = False):
    left = np.eye(4)
    targets = np.stack([np.eye(4), np.eye(4)])
    targets[0, :3, 3] = (0.1, 0, 0)
    targets[1, :3, 3] = (0, 0.5 if far else 0.2, 0)
    plan = SamplePlan(scene="irs-v0", subset="IRS", frame=3, key="irs-v0__000003", c2w_left=left,
                      c2w_right=right_camera(left, 0.1), c2w_targets=targets, target_ids=(0, 1),
                      K=np.array([[8.0, 0, 4], [0, 8.0, 3], [0, 0, 1]]), width=8, height=6, baseline=0.1, rho=0.2,
                      teacher_psnr=None)
    meta = json.loads(SampleMeta.from_plan(plan).to_json()) | {"target_frames": [5, 9], "target_coverage": [0.8, 0.7]}
    img = np.full((6, 8, 3), 128, np.uint8)
    sample = SampleImages(key=plan.key, left=img, right=img, targets=np.stack([img, img]),
                          masks=np.ones((2, 6, 8), bool), target_ids=(0, 1), meta=json.dumps(meta).encode())
    with shards.ShardWriter(out, "train", 4) as w:
        w.add(plan.key, encode_sample(sample))
    shards.write_index(out, "train")
    shards.write_stats(out, shards.collect_stats(out))


def test_irs_samples_pass_inspect(tmp_path):
    irs_dataset(tmp_path)
    report = inspect_dataset(tmp_path, progress=False)
    assert report.ok, report.problems


def test_irs_target_beyond_rho_is_flagged(tmp_path):
    irs_dataset(tmp_path, far=True)
    report = inspect_dataset(tmp_path, progress=False)
    assert any("farther than rho=0.2" in p for p in report.problems), report.problems


def test_inspect_missing_out(tmp_path, capsys):
    rc, text = run_cli(main, ["inspect", str(tmp_path / "none"), "--no-progress"], capsys)
    assert rc == 2 and "OUT" in text and "not a folder" in text


@pytest.mark.parametrize("name,content,message", [
    ("train/index.json", "{broken", "index.json: unreadable"),
    ("train/index.json", '{"shards": [{"name": "x"}]}', "index.json: unreadable"),
    ("stats.json", "[not json", "stats.json: unreadable"),
])
def test_broken_files_are_named(tmp_path, capsys, name, content, message):
    irs_dataset(tmp_path)
    (tmp_path / name).write_text(content)
    before = snapshot(tmp_path)
    rc, text = run_cli(main, ["inspect", str(tmp_path), "--no-progress", "--contact-sheet",
                              str(tmp_path.parent / f"{tmp_path.name}-sheet.png")], capsys)
    assert rc == 1 and message in text, text
    assert snapshot(tmp_path) == before


def test_negative_sheet_samples(tmp_path, capsys):
    rc, text = run_cli(main, ["inspect", str(tmp_path), "--sheet-samples", "-1"], capsys)
    assert rc == 2 and "--sheet-samples -1: must be >= 0" in text


# ------------------------------------------------- the contact sheet: replaced only as far as inspect wrote it


def inspect_argv(out, *extra) -> list[str]:
    return ["inspect", str(out), "--no-progress", *map(str, extra)]


def test_a_users_file_at_contact_sheet_is_kept(tmp_path, capsys):
    irs_dataset(tmp_path / "data")
    (tmp_path / "figure.png").write_bytes(b"the user's own figure")
    before = snapshot(tmp_path)
    rc, text = run_cli(main, inspect_argv(tmp_path / "data", "--contact-sheet", tmp_path / "figure.png"), capsys)
    assert rc == 2 and "error: --contact-sheet" in text and "figure.png: exists and was not written by " \
        "`scenesplat-stereo inspect` (no .written-by.figure.png beside it)" in text, text
    assert "samples checked" not in text and snapshot(tmp_path) == before  # refused before the dataset was read


def test_the_default_contact_sheet_of_another_tool_is_kept(tmp_path, capsys):
    irs_dataset(tmp_path)
    (tmp_path / "contact_sheet.png").write_bytes(b"another tool's sheet")
    before = snapshot(tmp_path)
    rc, text = run_cli(main, inspect_argv(tmp_path), capsys)
    assert rc == 2 and "contact_sheet.png: exists and was not written by `scenesplat-stereo inspect`" in text, text
    assert snapshot(tmp_path) == before


def test_a_contact_sheet_is_replaced_by_inspect_only_while_unchanged(tmp_path, capsys):
    irs_dataset(tmp_path / "data")
    sheet = tmp_path / "sheet.png"
    assert run_cli(main, inspect_argv(tmp_path / "data", "--contact-sheet", sheet), capsys)[0] == 0
    first = sheet.read_bytes()
    assert decode_image(first, "png").ndim == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == [".written-by.sheet.png", "data", "sheet.png"]  # no temp file
    assert run_cli(main, inspect_argv(tmp_path / "data", "--contact-sheet", sheet), capsys)[0] == 0  # its own: replaced
    assert sheet.read_bytes() == first
    sheet.write_bytes(first + b"the user's edit")
    before = snapshot(tmp_path)
    rc, text = run_cli(main, inspect_argv(tmp_path / "data", "--contact-sheet", sheet), capsys)
    assert rc == 2 and "sheet.png: exists and changed since `scenesplat-stereo inspect` wrote it" in text, text
    assert snapshot(tmp_path) == before


def test_contact_sheet_that_is_a_folder(tmp_path, capsys):
    irs_dataset(tmp_path / "data")
    (tmp_path / "sheets").mkdir()
    rc, text = run_cli(main, inspect_argv(tmp_path / "data", "--contact-sheet", tmp_path / "sheets"), capsys)
    assert rc == 2 and "--contact-sheet" in text and "sheets: is a folder" in text, text
    assert list((tmp_path / "sheets").iterdir()) == []
