"""Bad teacher folders: each is a ``Rejection`` naming the file and the field (never an exception that ends
discovery), or a warning when the teacher is still usable; the other teachers are found as usual."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.scene.teachers import discover_teachers
from tests.support.bad_input import snapshot, tiny_teacher


def inria(folder: Path, cameras: object, results: object | None = None, step: int = 100) -> Path:
    tiny_teacher(folder)
    (folder / "point_cloud" / f"iteration_{step}").mkdir(parents=True)
    shutil.move(folder / "point_cloud.ply", folder / "point_cloud" / f"iteration_{step}" / "point_cloud.ply")
    (folder / "transforms.json").unlink()
    (folder / "scene.json").unlink()
    (folder / "cameras.json").write_text(json.dumps(cameras))
    if results is not None:
        (folder / "results.json").write_text(json.dumps(results))
    return folder


CAM = {"position": [0, 0, 0], "rotation": np.eye(3).tolist(), "fx": 30, "fy": 30, "width": 32, "height": 24}

REJECTED = [  # (name, writer, part of the reason)
    ("results_entry_not_object", lambda f: inria(f, [CAM], {"ours_100": 31.5}), "results.json: ours_100: expected an object"),
    ("scalar_position", lambda f: inria(f, [CAM | {"position": 5}]), "cameras.json: [0].position: expected 3 numbers"),
    ("rotation_2x2", lambda f: inria(f, [CAM | {"rotation": [[1, 0], [0, 1]]}]), "[0].rotation: expected a 3x3 matrix"),
    ("camera_missing_fx", lambda f: inria(f, [{k: v for k, v in CAM.items() if k != "fx"}]), "[0].fx: missing"),
    ("cameras_empty", lambda f: inria(f, []), "cameras.json: file: expected a non-empty list"),
    ("results_no_entry", lambda f: inria(f, [CAM], {"train": {}}), "results.json: ours_<N>: no entry"),
]


def _edit_transforms(folder: Path, change) -> Path:
    tiny_teacher(folder)
    doc = json.loads((folder / "transforms.json").read_text())
    change(doc)
    (folder / "transforms.json").write_text(json.dumps(doc))
    return folder


REJECTED += [
    ("frames_empty", lambda f: _edit_transforms(f, lambda d: d.update(frames=[])), "transforms.json: frames: missing or zero"),
    ("non_rigid_pose", lambda f: _edit_transforms(f, lambda d: d["frames"][0].update(
        transform_matrix=(2 * np.eye(4)).tolist())), "frames[0].transform_matrix: not a rigid transform"),
    ("no_intrinsics", lambda f: _edit_transforms(f, lambda d: d.pop("fl_x")), "frames[0].fl_x: missing intrinsics"),
    ("negative_width", lambda f: _edit_transforms(f, lambda d: d.update(w=-5)), "frames[0].w: expected a positive"),
    ("bad_convention", lambda f: _edit_transforms(f, lambda d: d.update(camera_convention="left")),
     "camera_convention: expected 'opencv' or 'opengl'"),
]


@pytest.mark.parametrize("name,write,reason", REJECTED, ids=[c[0] for c in REJECTED])
def test_bad_teacher_is_rejected_by_name(tmp_path, name, write, reason):
    write(tmp_path / "bad")
    tiny_teacher(tmp_path / "good")
    before = snapshot(tmp_path)
    found = discover_teachers(tmp_path)
    assert [t.scene_id for t in found.teachers] == ["good"]
    assert len(found.rejected) == 1 and reason in found.rejected[0].reason, found.rejected[0].reason
    assert snapshot(tmp_path) == before  # discovery only reads


def test_psnr_of_another_step_is_not_silent(tmp_path):
    inria(tmp_path / "t", [CAM], {"ours_50": {"PSNR": 31.0}}, step=100)
    with pytest.warns(UserWarning, match="no PSNR for the checkpoint's step 100; using step 50"):
        found = discover_teachers(tmp_path)
    assert found.teachers[0].psnr == 31.0


def test_folder_name_with_spaces_and_dots_becomes_a_key_safe_id(tmp_path):
    tiny_teacher(tmp_path / "my room.v2")
    with pytest.warns(UserWarning, match="replaced by '_' in scene ids"):
        found = discover_teachers(tmp_path)
    assert [t.scene_id for t in found.teachers] == ["my_room_v2"]
