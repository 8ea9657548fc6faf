"""scenesplat_stereo.captured.colmap: generic pose recovery with pycolmap, against a synthetic sequence with known
poses (tests/support/irs_synthetic.py) and on degenerate inputs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from pipelines import irs_pose_recovery  # noqa: E402
from scenesplat_stereo.captured.colmap import (  # noqa: E402
    EXHAUSTIVE_MAX_FRAMES,
    PinholeCamera,
    RecoveryOptions,
    recover_poses,
    recovery_json,
)
from tests.support.irs_synthetic import align, cached_variant  # noqa: E402

FAST = dict(max_num_features=1024, num_threads=1)  # one thread: COLMAP runs deterministically


@pytest.fixture(scope="module")
def variant(tmp_path_factory):
    return cached_variant(tmp_path_factory.getbasetemp())


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import OpenImageIO as oiio

    assert oiio.ImageBuf(np.ascontiguousarray(rgb)).write(str(path))


def test_pinhole_parse_and_errors():
    cam = PinholeCamera.parse(" 480, 480.5,480,270 ", 960, 540)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (480.0, 480.5, 480.0, 270.0, 960, 540)
    np.testing.assert_array_equal(cam.K, [[480, 0, 480], [0, 480.5, 270], [0, 0, 1]])
    for bad in ("480,480,480", "a,b,c,d", "0,480,480,270", "480,-1,480,270", "nan,480,480,270", "1,2,3,4,5"):
        with pytest.raises(ValueError, match="intrinsics"):
            PinholeCamera.parse(bad, 960, 540)


def test_scaled_quarter_of_irs():
    # SPEC section 1: pixel u covers [u, u+1), so continuous coordinates scale by 240/960 = 135/540 = 1/4.
    cam = PinholeCamera(480.0, 480.0, 480.0, 270.0, 960, 540).scaled(240, 135)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (120.0, 120.0, 120.0, 67.5, 240, 135)


def test_matching_choice_and_checks(tmp_path):
    auto = RecoveryOptions()
    assert auto.matching_for(EXHAUSTIVE_MAX_FRAMES) == "exhaustive"
    assert auto.matching_for(EXHAUSTIVE_MAX_FRAMES + 1) == "sequential"
    assert RecoveryOptions(matching="sequential").matching_for(3) == "sequential"
    assert RecoveryOptions(matching="exhaustive").matching_for(10_000) == "exhaustive"
    with pytest.raises(ValueError, match="matching"):
        RecoveryOptions(matching="vocab").matching_for(10)
    with pytest.raises(FileNotFoundError, match="vocab"):
        RecoveryOptions(vocab_tree_path=tmp_path / "missing.bin").matching_for(10)
    tree = tmp_path / "tree.bin"
    tree.write_bytes(b"\0")
    assert RecoveryOptions(vocab_tree_path=tree).matching_for(500) == "sequential"


def test_atomic_write_json(tmp_path):
    from scenesplat_stereo.common.files import atomic_write_json

    path = tmp_path / "sub" / "a.json"
    atomic_write_json(path, {"x": [1, 2]})
    atomic_write_json(path, {"x": [3]})
    assert json.loads(path.read_text()) == {"x": [3]}
    assert sorted(p.name for p in path.parent.iterdir()) == ["a.json"]  # no temp file left behind
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_wrong_image_size_names_the_file(variant, tmp_path):
    odd = tmp_path / "odd.png"
    _write_png(odd, np.zeros((100, 200, 3), np.uint8))
    with pytest.raises(ValueError, match=r"odd\.png: image size 200x100 differs"):
        recover_poses([variant.folder / "l_1.png", odd], variant.camera, tmp_path / "work", RecoveryOptions(**FAST))


def test_too_few_and_blank_images(variant, tmp_path):
    one = recover_poses([variant.folder / "l_1.png"], variant.camera, tmp_path / "w1", RecoveryOptions(**FAST))
    assert one.registered == 0 and np.isnan(one.mean_reprojection_error) and one.c2w.shape == (0, 4, 4)
    assert recovery_json(one, ["l_1.png"]) == {"frames": [], "registered": 0, "mean_reprojection_error": None}
    blank = []
    for i in range(5):
        blank.append(tmp_path / f"blank_{i}.png")
        _write_png(blank[-1], np.full((135, 240, 3), 128, np.uint8))
    rec = recover_poses(blank, variant.camera, tmp_path / "w2", RecoveryOptions(**FAST))
    assert rec.registered == 0 and rec.num_input == 5


@pytest.mark.slow
def test_recover_synthetic_sequence(variant, tmp_path):
    paths = [variant.folder / f"l_{n}.png" for n in range(1, len(variant.c2w) + 1)]
    rec = recover_poses(paths, variant.camera, tmp_path / "work", RecoveryOptions(**FAST))
    assert rec.registered == len(paths) and rec.indices == list(range(len(paths)))
    assert rec.matching == "exhaustive" and rec.num_models >= 1
    # Intrinsics held fixed.
    assert rec.camera_params == [variant.camera.fx, variant.camera.fy, variant.camera.cx, variant.camera.cy]
    assert rec.mean_reprojection_error < 0.5
    np.testing.assert_allclose(rec.c2w[:, :3, :3] @ np.swapaxes(rec.c2w[:, :3, :3], 1, 2),
                               np.broadcast_to(np.eye(3), (len(paths), 3, 3)), atol=1e-9)
    a = align(rec.c2w, variant.c2w)
    assert a.max_centre_error <= 0.01 * variant.trajectory_length, a
    assert a.max_rotation_error_deg <= 0.5, a
    for obs in rec.observations:
        assert len(obs.xy) == len(obs.depth) == len(obs.point_ids) > 20
        assert (obs.depth > 0).all()
        assert ((obs.xy >= 0) & (obs.xy <= [variant.camera.width, variant.camera.height])).all()


@pytest.mark.slow
def test_recover_command_sequential(variant, tmp_path, capsys):
    # Names whose plain string order is not the frame order (frame_10 < frame_2): the command's natural
    # order and the staged names must keep sequential matching on neighbouring frames.
    images = tmp_path / "images"
    images.mkdir()
    for n in range(1, len(variant.c2w) + 1):
        os.symlink(variant.folder / f"l_{n}.png", images / f"frame_{n}.png")
    out = tmp_path / "poses.json"
    rc = irs_pose_recovery.main(["recover", "--images", str(images), "--intrinsics", "120,120,120,67.5",
                                 "--out", str(out), "--matching", "sequential", "--max-features", "1024",
                                 "--threads", "1"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert set(doc) == {"frames", "registered", "mean_reprojection_error"}
    assert doc["registered"] == len(doc["frames"]) == len(variant.c2w)
    assert 0 < doc["mean_reprojection_error"] < 0.5
    names = [f["image"] for f in doc["frames"]]
    assert names == [f"frame_{n}.png" for n in range(1, len(variant.c2w) + 1)]
    c2w = np.array([f["c2w"] for f in doc["frames"]])
    a = align(c2w, variant.c2w)
    assert a.max_centre_error <= 0.01 * variant.trajectory_length, a
    assert a.max_rotation_error_deg <= 0.5, a
    assert "sequential matching" in capsys.readouterr().out


def test_recover_command_errors(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert irs_pose_recovery.main(["recover", "--images", str(empty), "--intrinsics", "1,1,1,1",
                                   "--out", str(tmp_path / "p.json")]) == 2
    _write_png(empty / "a.png", np.zeros((8, 8, 3), np.uint8))
    assert irs_pose_recovery.main(["recover", "--images", str(empty), "--intrinsics", "1,1,1",
                                   "--out", str(tmp_path / "p.json")]) == 2
    err = capsys.readouterr().err
    assert "no images" in err and "fx,fy,cx,cy" in err
    assert not (tmp_path / "p.json").exists()
