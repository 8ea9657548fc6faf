"""Teacher discovery (SPEC section 3): each layout from small fixture folders, malformed teachers."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.build.protocol import filter_teachers, plan_scene
from scenesplat_stereo.scene.cameras import look_at
from scenesplat_stereo.scene.gaussians import GaussianScene, load_ply, save_ply
from scenesplat_stereo.scene.teachers import OrbitSpec, Rejection, discover_teachers, resolve_trajectory, summary_table

# An OpenCV camera at (1, 2, 3) looking along world +x with y down: its OpenGL c2w flips columns 1, 2.
POSE_CV = look_at(np.array([1.0, 2.0, 3.0]), np.array([5.0, 2.0, 3.0]))
POSE_GL = POSE_CV @ np.diag([1.0, -1.0, -1.0, 1.0])
NAN_POSE = POSE_CV + np.diag([np.nan, 0.0, 0.0, 0.0])


def write_ply(path: Path, sh_degree: int = 0, n: int = 12, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    k = (sh_degree + 1) ** 2
    q = rng.normal(size=(n, 4))
    scene = GaussianScene(rng.normal(size=(n, 3)).astype(np.float32),
                          (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                          rng.uniform(0.01, 0.1, (n, 3)).astype(np.float32),
                          rng.uniform(0.1, 0.9, n).astype(np.float32),
                          rng.normal(size=(n, k, 3)).astype(np.float32), sh_degree)
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_ply(scene, path)


def write_json(path: Path, data: object) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


def transforms(poses: list[np.ndarray], **top) -> dict:
    base = {"fl_x": 60.0, "fl_y": 62.0, "cx": 31.0, "cy": 23.0, "w": 64, "h": 48}
    base.update(top)
    return {**base, "frames": [{"file_path": f"images/{i:03d}.jpg", "transform_matrix": np.asarray(p).tolist()}
                               for i, p in enumerate(poses)]}


def make_scenesplat(folder: Path, psnr: float = 33.5) -> Path:
    write_ply(folder / "ckpts/point_cloud_7000.ply", sh_degree=0)
    write_ply(folder / "ckpts/point_cloud_30000.ply", sh_degree=2)
    write_json(folder / "stats/val_step7000.json", {"psnr": 20.0})
    write_json(folder / "stats/val_step30000.json", {"psnr": psnr, "ssim": 0.9})
    write_json(folder / "transforms_train.json", transforms([POSE_GL, np.eye(4)]))
    return folder


def make_inria(folder: Path) -> Path:
    write_ply(folder / "point_cloud/iteration_7000/point_cloud.ply", sh_degree=0)
    write_ply(folder / "point_cloud/iteration_30000/point_cloud.ply", sh_degree=3)
    cams = [{"id": i, "img_name": f"IMG_{i}", "width": 80, "height": 60, "fx": 70.0, "fy": 71.0,
             "position": POSE_CV[:3, 3].tolist(), "rotation": POSE_CV[:3, :3].tolist()} for i in range(3)]
    write_json(folder / "cameras.json", cams)
    write_json(folder / "results.json", {"ours_7000": {"PSNR": 28.0}, "ours_30000": {"PSNR": 36.25}})
    return folder


def make_plain(folder: Path, scene: dict | None = None, tf: dict | None = None) -> Path:
    write_ply(folder / "point_cloud.ply", sh_degree=1)
    write_json(folder / "transforms.json", tf if tf is not None else
               transforms([POSE_CV] * 4, camera_convention="opencv"))
    if scene is not None:
        write_json(folder / "scene.json", scene)
    return folder


def test_scenesplat_layout(tmp_path):
    make_scenesplat(tmp_path / "ScanNetGS" / "scene0000_00")
    found = discover_teachers(tmp_path)
    assert not found.rejected
    (t,) = found.teachers
    assert (t.scene_id, t.subset, t.layout) == ("scene0000_00", "ScanNetGS", "scenesplat")
    assert t.ply_path.name == "point_cloud_30000.ply" and t.sh_degree == 2  # highest step
    assert t.psnr == 33.5  # stats of that step
    assert t.camera_convention == "opengl" and t.trajectory == "transforms_train.json"
    np.testing.assert_allclose(t.c2w[0], POSE_CV, atol=1e-12)  # OpenGL file -> OpenCV in memory
    np.testing.assert_allclose(t.c2w[1], np.diag([1.0, -1.0, -1.0, 1.0]))
    np.testing.assert_allclose(t.Ks[0], [[60, 0, 31], [0, 62, 23], [0, 0, 1]])
    assert (t.width, t.height, t.num_frames) == (64, 48, 2)
    assert t.frame_names == ["images/000.jpg", "images/001.jpg"]


def test_opengl_camera_looks_down_minus_z(tmp_path):
    # nerfstudio identity pose: camera looks down world -z; in OpenCV its +z axis must be world -z.
    make_plain(tmp_path / "s", tf=transforms([np.eye(4)]))
    (t,) = discover_teachers(tmp_path).teachers
    np.testing.assert_allclose(t.c2w[0][:3, 2], [0, 0, -1])
    np.testing.assert_allclose(t.c2w[0][:3, 1], [0, -1, 0])


def test_inria_layout(tmp_path):
    make_inria(tmp_path / "ScanNetPPGS-V2" / "0a5c013435")
    (t,) = discover_teachers(tmp_path).teachers
    assert (t.layout, t.subset, t.sh_degree, t.psnr) == ("inria", "ScanNetPPGS-V2", 3, 36.25)
    assert t.ply_path.parent.name == "iteration_30000"
    assert t.camera_convention == "opencv" and t.frame_names == ["IMG_0", "IMG_1", "IMG_2"]
    np.testing.assert_allclose(t.c2w, np.broadcast_to(POSE_CV, (3, 4, 4)), atol=1e-12)
    np.testing.assert_allclose(t.Ks[0], [[70, 0, 40], [0, 71, 30], [0, 0, 1]])  # principal point centred
    assert (t.width, t.height) == (80, 60)


def test_inria_without_results_has_no_psnr(tmp_path):
    make_inria(tmp_path / "a")
    (tmp_path / "a/results.json").unlink()
    (t,) = discover_teachers(tmp_path).teachers
    assert t.psnr is None
    assert filter_teachers([t])[0] == [] and filter_teachers([t], None)[0] == [t]


def test_plain_layout_scene_json(tmp_path):
    make_plain(tmp_path / "misc" / "room", scene={"psnr": 41.5, "subset": "MyRooms"})
    make_plain(tmp_path / "misc" / "hall")
    found = discover_teachers(tmp_path)
    hall, room = found.teachers
    assert (room.layout, room.psnr, room.subset, room.sh_degree) == ("plain", 41.5, "MyRooms", 1)
    assert (hall.psnr, hall.subset) == (None, "default")  # "misc" is not a subset-style name
    np.testing.assert_allclose(room.c2w[0], POSE_CV, atol=1e-12)  # "opencv" in the file: no flip
    assert (room.baseline, room.rho) == (None, None)


def test_scene_json_baseline_and_rho(tmp_path):
    make_plain(tmp_path / "desk", scene={"psnr": 41.5, "baseline": 0.063, "rho": 0.05})
    (desk,) = discover_teachers(tmp_path).teachers
    assert (desk.baseline, desk.rho) == (0.063, 0.05)


def test_scene_json_convention_and_per_frame_intrinsics(tmp_path):
    tf = transforms([POSE_CV, POSE_CV], w=64, h=48)
    tf["frames"][1].update({"fl_x": 30.0, "fl_y": 31.0, "cx": 15.0, "cy": 11.0})
    make_plain(tmp_path / "s", scene={"camera_convention": "opencv"}, tf=tf)
    (t,) = discover_teachers(tmp_path).teachers
    assert t.camera_convention == "opencv"
    np.testing.assert_allclose(t.c2w[1], POSE_CV, atol=1e-12)
    np.testing.assert_allclose(t.Ks[1], [[30, 0, 15], [0, 31, 11], [0, 0, 1]])


def test_camera_angle_x_and_default_centre(tmp_path):
    tf = {"camera_angle_x": 2 * math.atan(0.5), "w": 40, "h": 30,
          "frames": [{"transform_matrix": np.eye(4).tolist()}]}
    make_plain(tmp_path / "s", tf=tf)
    (t,) = discover_teachers(tmp_path).teachers
    np.testing.assert_allclose(t.Ks[0], [[40, 0, 20], [0, 40, 15], [0, 0, 1]])
    assert t.frame_names == ["frame_000000"]


def test_mixed_frame_sizes_are_rescaled_with_warning(tmp_path):
    tf = transforms([POSE_CV] * 3)
    tf["frames"][2].update({"w": 128, "h": 96, "fl_x": 120.0, "fl_y": 124.0, "cx": 62.0, "cy": 46.0})
    make_plain(tmp_path / "s", tf=tf)
    with pytest.warns(UserWarning, match="1 of 3 frames are not 64x48"):
        (t,) = discover_teachers(tmp_path).teachers
    np.testing.assert_allclose(t.Ks[2], t.Ks[0])


def test_root_itself_is_a_teacher(tmp_path):
    make_plain(tmp_path / "ReplicaGS", scene={"psnr": 41.0})
    (t,) = discover_teachers(tmp_path / "ReplicaGS").teachers
    assert t.scene_id == "ReplicaGS"


def test_orbit_teacher_resolved_from_median(tmp_path):
    write_ply(tmp_path / "obj" / "model.ply", n=50)  # the single .ply of a plain folder
    found = discover_teachers(tmp_path)
    assert found.teachers == [] and "trajectory" in found.rejected[0].reason
    orbit = OrbitSpec.parse("radius=3,frames=5,elevation=10,size=32x24,fov=90,up=+z")
    (t,) = discover_teachers(tmp_path, orbit).teachers
    assert t.c2w is None and t.trajectory == "orbit" and t.num_frames == 5
    np.testing.assert_allclose(t.Ks[0], [[16, 0, 16], [0, 16, 12], [0, 0, 1]], atol=1e-12)
    means = load_ply(t.ply_path).means
    r = resolve_trajectory(t, means)
    median = np.median(means.astype(np.float64), axis=0)
    np.testing.assert_allclose(np.linalg.norm(r.c2w[:, :3, 3] - median, axis=1), 3.0)
    np.testing.assert_allclose(r.c2w[:, 2, 3] - median[2], 3 * math.sin(math.radians(10)))
    assert resolve_trajectory(r, means) is r
    assert len(plan_scene(r, "train", baseline=0.1, rho=0.2)) == 5
    with pytest.raises(ValueError, match="means"):
        resolve_trajectory(t, np.full((3, 3), np.nan))


@pytest.mark.parametrize("text,error", [("", "radius is required"), ("radius=-1", "radius must be a finite number > 0"),
                                        ("radius=1,up=z", "unknown"), ("radius=1,fov=200", "fov")])
def test_orbit_spec_parse_errors(text, error):
    with pytest.raises(ValueError, match=error):
        OrbitSpec.parse(text)


MALFORMED = {
    # scene: (how to break it, expected words in the reason)
    "bad_json": (lambda f: (f / "transforms.json").write_text("{not json"), "transforms.json: file: unreadable JSON"),
    "no_matrix": (lambda f: write_json(f / "transforms.json", {**transforms([POSE_CV]), "frames": [
        {"file_path": "a"}]}), "frames[0].transform_matrix: missing"),
    "nan_matrix": (lambda f: write_json(f / "transforms.json", transforms([POSE_CV, NAN_POSE])),
                   "frames[1].transform_matrix: non-finite value"),  # json writes NaN, Python reads it
    "scaled_rotation": (lambda f: write_json(f / "transforms.json", transforms([np.diag([2.0, 2.0, 2.0, 1.0])])),
                        "not a rigid transform"),
    "mirror": (lambda f: write_json(f / "transforms.json", transforms([np.diag([-1.0, 1.0, 1.0, 1.0])])),
               "rotation has det <= 0"),
    "no_focal": (lambda f: write_json(f / "transforms.json", {k: v for k, v in transforms([POSE_CV]).items()
                                                                if k not in ("fl_x", "fl_y")}),
                 "frames[0].fl_x: missing intrinsics"),
    "no_size": (lambda f: write_json(f / "transforms.json", {k: v for k, v in transforms([POSE_CV]).items()
                                                               if k != "w"}), "frames[0].w/h: missing image size"),
    "zero_frames": (lambda f: write_json(f / "transforms.json", transforms([])), "frames: missing or zero frames"),
    "bad_focal": (lambda f: write_json(f / "transforms.json", transforms([POSE_CV], fl_x=-5.0)),
                  "frames[0].fl_x: expected a positive number"),
    "no_trajectory": (lambda f: (f / "transforms.json").unlink(), "trajectory: no transforms.json"),
    "not_ply": (lambda f: (f / "point_cloud.ply").write_text("hello"), "point_cloud.ply: header: not a PLY"),
    "bad_convention": (lambda f: write_json(f / "scene.json", {"camera_convention": "blender"}),
                       "scene.json: camera_convention"),
    "conflict": (lambda f: (write_json(f / "scene.json", {"camera_convention": "opengl"}),
                            write_json(f / "transforms.json", transforms([POSE_CV], camera_convention="opencv"))),
                 "'opencv' but scene.json says 'opengl'"),
    "bad_psnr": (lambda f: write_json(f / "scene.json", {"psnr": "high"}), "scene.json: psnr: expected a finite"),
    "bad_baseline": (lambda f: write_json(f / "scene.json", {"baseline": -0.06}),
                     "scene.json: baseline: expected a positive number"),
    "bad_rho": (lambda f: write_json(f / "scene.json", {"rho": "far"}), "scene.json: rho: expected a finite"),
    "two_plys": (lambda f: ((f / "point_cloud.ply").rename(f / "a.ply"), write_ply(f / "b.ply")),
                 "scene file: 2 scene files (a.ply, b.ply) and none named point_cloud.ply"),
}


def test_malformed_teachers_are_rejected_with_reasons(tmp_path):
    root = tmp_path / "teachers"
    make_plain(root / "good_plain")
    make_scenesplat(root / "good_scenesplat")
    for name, (breaker, _) in MALFORMED.items():
        folder = make_plain(root / name)
        breaker(folder)
    (root / "empty").mkdir()
    ss = make_scenesplat(root / "ss_no_psnr_key")
    write_json(ss / "stats/val_step30000.json", {"ssim": 0.9})
    inria = make_inria(root / "inria_no_fx")
    cams = json.loads((inria / "cameras.json").read_text())
    del cams[1]["fx"]
    write_json(inria / "cameras.json", cams)
    inria2 = make_inria(root / "inria_bad_results")
    write_json(inria2 / "results.json", {"ours_30000": {"SSIM": 0.9}})
    found = discover_teachers(root)
    assert sorted(t.scene_id for t in found.teachers) == ["good_plain", "good_scenesplat"]
    reasons = {r.scene_id: r.reason for r in found.rejected}
    expected = {name: words for name, (_, words) in MALFORMED.items()}
    expected.update({"empty": "layout: no teacher scene", "ss_no_psnr_key": "val_step30000.json: psnr: missing",
                     "inria_no_fx": "cameras.json: [1].fx: missing",
                     "inria_bad_results": "results.json: ours_30000.PSNR: missing"})
    assert set(reasons) == set(expected)
    for name, words in expected.items():
        assert words in reasons[name], (name, reasons[name])
    table = summary_table(found)
    assert "default" in table and f"dropped ({len(expected)})" in table
    assert "frames[1].transform_matrix: non-finite value" in table


def test_duplicate_and_dotted_scene_ids(tmp_path):
    make_plain(tmp_path / "ScanNetGS" / "scene0000_00")
    make_plain(tmp_path / "ReplicaGS" / "scene0000_00")
    make_plain(tmp_path / "ReplicaGS" / "room.v2")
    with pytest.warns(UserWarning, match="1 scene folder names contain '.'"):
        found = discover_teachers(tmp_path)
    assert sorted(t.scene_id for t in found.teachers) == ["room_v2", "scene0000_00"]
    (dup,) = found.rejected
    assert "duplicate" in dup.reason and dup.subset == "ScanNetGS"


def test_summary_table_counts(tmp_path):
    make_plain(tmp_path / "ScanNetGS" / "a", scene={"psnr": 31.0})
    make_plain(tmp_path / "ScanNetGS" / "b", scene={"psnr": 29.0})
    make_plain(tmp_path / "ScanNetGS" / "c", scene={"psnr": 38.0})
    (tmp_path / "ScanNetGS" / "d").mkdir()
    found = discover_teachers(tmp_path)
    kept, dropped = filter_teachers(found.teachers)
    assert [t.scene_id for t in kept] == ["a", "c"]
    table = summary_table(found, dropped, per_teacher=True)
    lines = table.splitlines()
    assert lines[0].split() == ["subset", "found", "kept", "dropped"]
    assert lines[1].split() == ["ScanNetGS", "4", "2", "2"]  # found = kept + dropped (d is empty)
    assert lines[2].split() == ["total", "4", "2", "2"]
    assert "PSNR 29.00 dB not above 30.0 dB" in table and "kept teachers:" in table
    assert "38.00" in table and "transforms.json (opencv)" in table


def test_missing_root(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a folder"):
        discover_teachers(tmp_path / "nope")


def test_real_guitar_teacher(shared_data):
    root = shared_data / "teachers"
    found = discover_teachers(root)
    assert found.teachers == [] and isinstance(found.rejected[0], Rejection)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (t,) = discover_teachers(root, OrbitSpec(radius=6.0, n_frames=4, width=32, height=24)).teachers
    assert t.ply_path.name == "point_cloud.ply" and t.sh_degree == 0 and t.layout == "plain"


def test_a_folder_holding_one_scene_file_of_any_format_is_a_plain_teacher(tmp_path):
    """.compressed.ply, .spz, .sog, .splat, an unbundled SOG (meta.json + WebP) and a streamed SOG folder."""
    from tests.scenesplat_stereo.scene.test_lod import make_streamed

    from scenesplat_stereo.scene.scene_files import FORMATS, save_scene
    from tests.support.ply_helpers import random_scene
    from tests.support.sog_helpers import make_sog

    root = tmp_path / "teachers"
    scene = random_scene(np.random.default_rng(0), 40, 1)
    for name in ("compressed-ply", "spz", "sog"):
        save_scene(scene, root / name / f"scene{FORMATS[name].suffix}", name)
    (root / "splat").mkdir()
    (root / "splat" / "scene.splat").write_bytes(np.zeros(3, np.dtype([("m", "<f4", 3), ("s", "<f4", 3),
                                                                       ("c", "u1", 8)])).tobytes())
    make_sog(root / "sog_folder", 20, 2)
    make_streamed(root / "streamed")
    found = discover_teachers(root, OrbitSpec(radius=2.0, n_frames=2))
    assert not found.rejected, found.rejected
    got = {t.scene_id: (t.layout, t.sh_degree, t.ply_path.name) for t in found.teachers}
    assert got == {"compressed-ply": ("plain", 1, "scene.compressed.ply"), "spz": ("plain", 1, "scene.spz"),
                   "sog": ("plain", 1, "scene.sog"), "splat": ("plain", 0, "scene.splat"),
                   "sog_folder": ("plain", 2, "meta.json"), "streamed": ("plain", 1, "lod-meta.json")}
