"""protocol.SampleMeta: the one reader/writer of a sample's JSON (SPEC section 5)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from scenesplat_stereo.build.protocol import SamplePlan
from scenesplat_stereo.shards.sample import SampleMeta, SampleMetaError
from scenesplat_stereo.shards.webdataset import iter_shard


def plan() -> SamplePlan:
    c2w = np.eye(4)
    c2w[:3, 3] = (1.0, 2.0, 3.0)
    right = c2w.copy()
    right[0, 3] += 0.05
    return SamplePlan(scene="s0", subset="ScanNetGS", frame=7, key="s0__000007", c2w_left=c2w, c2w_right=right,
                      c2w_targets=np.stack([c2w] * 3), target_ids=(0, 4, 9),
                      K=np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), width=64, height=48,
                      baseline=0.05, rho=0.1, teacher_psnr=31.5)


def test_json_has_the_spec_fields_in_order_and_round_trips():
    meta = SampleMeta.from_plan(plan())
    data = meta.to_json()
    doc = json.loads(data)
    assert list(doc) == ["key", "scene", "subset", "frame", "width", "height", "K", "baseline", "rho", "teacher_psnr",
                         "c2w_left", "c2w_right", "target_ids", "targets", "camera_convention"]
    assert b" " not in data  # compact, as the builder always wrote it
    assert doc["frame"] == 7 and doc["width"] == 64 and doc["K"][0][2] == 32.0 and doc["target_ids"] == [0, 4, 9]
    assert doc["c2w_left"][0][3] == 1.0 and len(doc["targets"]) == 3 and doc["camera_convention"] == "opencv"
    back = SampleMeta.from_json(data, "x.json")
    assert back == meta and back.to_json() == data
    assert back.num_targets == 3 and back.targets.shape == (3, 4, 4) and not back.K.flags.writeable
    assert back != replace(meta, frame=8)


def test_optional_fields_irs_extras_and_no_psnr():
    meta = replace(SampleMeta.from_plan(plan()), c2w_right=None, teacher_psnr=None,
                   target_frames=(3, 9, 12), target_coverage=(0.8, 0.5, 0.41))
    doc = json.loads(meta.to_json())
    assert "c2w_right" not in doc and doc["teacher_psnr"] is None
    assert list(doc)[-2:] == ["target_frames", "target_coverage"] and doc["target_frames"] == [3, 9, 12]
    assert SampleMeta.from_json(meta.to_json(), "x") == meta


def test_builder_json_reads_back_equal_to_its_plan(demo_dataset):
    import warnings

    from scenesplat_stereo.build.protocol import plan_scene
    from scenesplat_stereo.scene.teachers import discover_teachers

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        teachers = discover_teachers(demo_dataset.parent / "teachers", None).teachers
        plans = {p.key: p for t in teachers for split in ("train", "val") for p in plan_scene(t, split)}
    index = json.loads((demo_dataset / "val" / "index.json").read_text())
    seen = 0
    for shard in index["shards"]:
        for key, members in iter_shard(demo_dataset / "val" / shard["name"]):
            meta = SampleMeta.from_json(members["json"], key)
            assert meta == SampleMeta.from_plan(plans[key]) and meta.to_json() == members["json"]
            np.testing.assert_array_equal(meta.targets, plans[key].c2w_targets)
            seen += 1
    assert seen == 5


def _doc() -> dict:
    return json.loads(SampleMeta.from_plan(plan()).to_json())


def _set(path, value):
    def edit(doc):
        if isinstance(path, tuple):
            doc[path[0]][path[1]][path[2]] = value
        else:
            doc[path] = value
        return doc
    return edit


@pytest.mark.parametrize("edit, field", [
    (lambda d: {k: v for k, v in d.items() if k != "K"}, "missing fields ['K']"),
    (lambda d: {k: v for k, v in d.items() if k != "targets"}, "missing fields ['targets']"),
    (lambda d: d | {"extra": 1}, "unknown fields ['extra']"),
    (_set("key", "a.b"), "'key'"),
    (_set("key", ""), "'key'"),
    (_set("scene", 3), "'scene'"),
    (_set("subset", ""), "'subset'"),
    (_set("frame", -1), "'frame'"),
    (_set("frame", 1.5), "'frame'"),
    (_set("frame", True), "'frame'"),
    (_set("width", 0), "'width'"),
    (_set("height", "48"), "'height'"),
    (_set(("K", 0, 0), float("nan")), "'K'"),
    (_set(("K", 1, 1), -100.0), "'K'"),
    (_set("K", [[1.0, 0.0], [0.0, 1.0]]), "'K'"),
    (_set("K", "eye"), "'K'"),
    (_set("baseline", 0.0), "'baseline'"),
    (_set("baseline", -0.05), "'baseline'"),
    (_set("baseline", float("inf")), "'baseline'"),
    (_set("rho", -0.1), "'rho'"),
    (_set("teacher_psnr", "high"), "'teacher_psnr'"),
    (_set(("c2w_left", 0, 3), float("inf")), "'c2w_left'"),
    (_set("c2w_left", np.eye(3).tolist()), "'c2w_left'"),
    (_set("c2w_right", [[1.0]]), "'c2w_right'"),
    (_set("targets", []), "'targets': no targets"),
    (_set("targets", [np.eye(3).tolist()]), "'targets'"),
    (_set("targets", "none"), "'targets'"),
    (_set("target_ids", [0, 1]), "'target_ids'"),
    (_set("target_ids", [0, 0, 1]), "'target_ids': repeated"),
    (_set("target_ids", [0, 1, 100]), "'target_ids'"),
    (_set("target_ids", [0, 1, -1]), "'target_ids'"),
    (_set("camera_convention", "opengl"), "'camera_convention'"),
    (_set("target_frames", [1, 2]), "'target_frames'"),
    (_set("target_coverage", [0.5, 0.5, 1.5]), "'target_coverage'"),
])
def test_every_malformed_field_is_named(edit, field):
    data = json.dumps(edit(_doc())).encode()
    with pytest.raises(SampleMetaError) as err:
        SampleMeta.from_json(data, "shard-000003.tar:s0__000007.json")
    assert str(err.value).startswith("shard-000003.tar:s0__000007.json: ") and field in str(err.value)


@pytest.mark.parametrize("data, message", [(b"{not json", "not valid JSON"), (b"[1, 2]", "expected a JSON object"),
                                           (b"\xff\xfe", "not valid JSON")])
def test_unreadable_json(data, message):
    with pytest.raises(SampleMetaError, match=message):
        SampleMeta.from_json(data, "src")
    assert issubclass(SampleMetaError, ValueError)


def test_json_bytes_match_hand_written_json():
    c2w = np.eye(4)
    c2w[:3, 3] = (1.0, 2.0, 3.0)
    plan = SamplePlan(scene="s0", subset="ScanNetGS", frame=7, key="s0__000007", c2w_left=c2w,
                      c2w_right=c2w + 0.5, c2w_targets=np.stack([c2w] * 3), target_ids=(0, 1, 2),
                      K=np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), width=64, height=48,
                      baseline=0.05, rho=0.1, teacher_psnr=31.5)
    doc = json.loads(SampleMeta.from_plan(plan).to_json())
    for f in ("scene", "subset", "frame", "width", "height", "K", "baseline", "rho", "teacher_psnr", "c2w_left", "targets"):
        assert f in doc
    assert doc["frame"] == 7 and doc["width"] == 64 and doc["K"][0][2] == 32
    assert doc["c2w_left"][0][3] == 1.0 and len(doc["targets"]) == 3 and doc["target_ids"] == [0, 1, 2]
    assert doc["teacher_psnr"] == 31.5 and doc["camera_convention"] == "opencv"
    # The exact bytes: compact JSON, fields in SPEC order, float64 values as written (expected written here
    # by hand, not from sample_json).
    right = (c2w + 0.5).tolist()
    want = {"key": "s0__000007", "scene": "s0", "subset": "ScanNetGS", "frame": 7, "width": 64, "height": 48,
            "K": [[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]], "baseline": 0.05, "rho": 0.1,
            "teacher_psnr": 31.5, "c2w_left": c2w.tolist(), "c2w_right": right, "target_ids": [0, 1, 2],
            "targets": [c2w.tolist()] * 3, "camera_convention": "opencv"}
    assert SampleMeta.from_plan(plan).to_json() == json.dumps(want, separators=(",", ":")).encode()
