"""Bad input to ``scenesplat-stereo import multiview``: one line naming the file or flag, exit 2, and an
existing OUT left exactly as it was (an earlier good import stays)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from tests.scenesplat_stereo.captured.test_multiview import BASELINE, FOCAL, SIZE, write_line_set

from scenesplat_stereo.cli import main as cli_main
from scenesplat_stereo.shards.encode import encode_png
from tests.support.bad_input import refusal, snapshot

FLAGS = ["--focal", FOCAL, "--baseline", BASELINE, "--pair", "1,3"]


@pytest.fixture(scope="module")
def good_set(tmp_path_factory):
    folder = tmp_path_factory.mktemp("good") / "plane"
    write_line_set(folder)
    return folder


def _png(path, shape, value=100, dtype=np.uint8):
    path.write_bytes(encode_png(np.full(shape, value, dtype=dtype)))


REFUSED = [  # (name, damage to a copy of the set, extra flags, part of the message)
    ("view_gap", lambda f: (f / "im2.png").unlink(), [], "views [2] missing"),
    ("view_twice", lambda f: shutil.copy(f / "im2.png", f / "im2.ppm"), [], "view 2 is also"),
    ("two_views", lambda f: [(f / f"im{k}.png").unlink() for k in (2, 3, 4)], [], "2 views"),
    ("view_other_size", lambda f: _png(f / "im4.png", (SIZE, SIZE + 2, 3)), [], "im4.png: 50x48 pixels"),
    ("view_garbage", lambda f: (f / "im0.png").write_bytes(b"not an image"), [], "im0.png"),
    ("disparity_other_size", lambda f: _png(f / "disp1.png", (SIZE, SIZE - 1, 1)), [], "disp1.png: decoded"),
    ("disparity_rgb", lambda f: _png(f / "disp1.png", (SIZE, SIZE, 3)), [], "disp1.png: decoded"),
    ("disparity_unknown", lambda f: _png(f / "disp1.png", (SIZE, SIZE, 1), 0), [], "disp1.png: no known"),
    ("disparity_scale", lambda f: None, ["--disparity-scale", "0.5"], "is --disparity-scale right"),
    ("pair_outside", lambda f: None, ["--pair", "1,5"], "--pair 1,5"),
    ("pair_reversed", lambda f: None, ["--pair", "3,1"], "--pair 3,1"),
    ("pair_malformed", lambda f: None, ["--pair", "1"], "--pair"),
    ("positions_count", lambda f: None, ["--view-positions", "0,1"], "--view-positions: 2 numbers for 5"),
    ("positions_pair", lambda f: None, ["--view-positions=-1,0.5,1,1.5,2"], "view 1 (L) must be at 0"),
    ("positions_order", lambda f: None, ["--view-positions=-1,0,2,1,3"], "view 3 (1) is not right of view 2"),
    ("positions_text", lambda f: None, ["--view-positions", "0,a"], "--view-positions"),
    ("focal_tiny", lambda f: None, ["--focal", "1"], "--focal 1: a 175.2 deg"),
    ("focal_huge", lambda f: None, ["--focal", "5000"], "--focal 5000"),
    ("focal_negative", lambda f: None, ["--focal", "-450"], "--focal"),
    ("baseline_millimetres", lambda f: None, ["--baseline", "65"], "--baseline 65: expected metres"),
    ("baseline_zero", lambda f: None, ["--baseline", "0"], "--baseline"),
]


@pytest.mark.parametrize("damage, extra, message", [r[1:] for r in REFUSED], ids=[r[0] for r in REFUSED])
def test_a_refused_import_names_the_problem_and_leaves_out_alone(good_set, tmp_path, capsys, damage, extra, message):
    folder = tmp_path / "root" / "plane"
    shutil.copytree(good_set, folder)
    out = tmp_path / "out"
    assert cli_main(["import", "multiview", str(folder), "--out", str(out)] + [str(a) for a in FLAGS]) == 0
    before = snapshot(out)
    capsys.readouterr()
    damage(folder)
    rc, err = refusal(cli_main, ["import", "multiview", folder.parent, "--out", out] + FLAGS + extra, capsys)
    assert rc == 2 and message in err and len(err.splitlines()) == 1, err
    assert snapshot(out) == before


def test_no_set_and_not_a_folder(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    for root, message in ((tmp_path / "empty", "no set"), (tmp_path / "absent", "not a folder")):
        rc, err = refusal(cli_main, ["import", "multiview", root, "--out", tmp_path / "out"] + FLAGS, capsys)
        assert rc == 2 and message in err and not (tmp_path / "out").exists(), err


def test_an_import_never_replaces_another_dataset(good_set, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "test").mkdir(parents=True)
    (out / "test" / "index.json").write_text("{}")
    before = snapshot(out)
    rc, err = refusal(cli_main, ["import", "multiview", good_set, "--out", out] + FLAGS, capsys)
    assert rc == 2 and "--out" in err and "not written by `scenesplat-stereo import multiview`" in err
    assert snapshot(out) == before
