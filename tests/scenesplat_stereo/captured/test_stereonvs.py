"""``scenesplat-stereo import stereonvs``: LLFF cameras, the protocol, the metric scale, the checks, and the
shards, on a fixture rendered at known stereo cameras (tests/support/stereonvs_fixture.py)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from scenesplat_stereo.build.demo import make_room
from scenesplat_stereo.build.inspection import inspect_dataset
from scenesplat_stereo.captured import stereonvs as S
from scenesplat_stereo.captured.llff import LlffError, llff_to_opencv, opencv_to_llff, read_poses_bounds
from scenesplat_stereo.cli import main as cli_main
from scenesplat_stereo.common.ownership import write_manifest
from scenesplat_stereo.scene.cameras import translation
from scenesplat_stereo.shards.encode import decode_image, encode_jpeg
from scenesplat_stereo.shards.sample import SampleMeta
from scenesplat_stereo.shards.webdataset import iter_shard
from sgmodel.data.loader import eval_batches
from tests.support.stereonvs_fixture import (BASELINE, FOCAL, IMAGE_SIZE, POSES_SIZE, llff_row, render, rotation_about,
                                             true_K)


def samples(out):
    """{key: (meta, members)} of every test shard of ``out``."""
    found = {}
    for tar in sorted((out / "test").glob("shard-*.tar")):
        for key, members in iter_shard(tar):
            found[key] = (SampleMeta.from_json(members["json"], key), members)
    return found


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0 ** 2 / np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


# ---------------------------------------------------------------------------------------------- LLFF
def test_llff_axes_of_a_known_camera():
    # An OpenGL-style camera at (1, 2, 3) looking down world -z with world +y up: LLFF columns are
    # down = (0, -1, 0), right = (1, 0, 0), backwards = (0, 0, 1).
    m = np.array([[0.0, 1.0, 0.0, 1.0], [-1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]])
    c2w = llff_to_opencv(m)
    np.testing.assert_array_equal(c2w[:3, :3], np.diag([1.0, -1.0, -1.0]))  # x right, y down, z forward
    np.testing.assert_array_equal(c2w[:3, 3], [1.0, 2.0, 3.0])
    point = np.array([1.0, 3.0, -2.0])  # 5 in front of the camera, 1 above its axis
    cam = c2w[:3, :3].T @ (point - c2w[:3, 3])
    np.testing.assert_allclose(cam, [0.0, -1.0, 5.0])  # in front (z > 0), above the axis (y < 0: up)


def test_llff_matches_stereonerfs_conversion_and_round_trips():
    rng = np.random.default_rng(0)
    mats = []
    for _ in range(6):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        mats.append(np.column_stack([q * np.sign(np.linalg.det(q)), rng.normal(size=3)]))
    mats = np.array(mats)
    # StereoNeRF's data/llff_stereo.py: [col 1, -col 0, col 2, col 3] (OpenGL), then @ diag(1, -1, -1, 1).
    gl = np.concatenate([mats[..., 1:2], -mats[..., :1], mats[..., 2:4]], -1)
    theirs = gl @ np.diag([1.0, -1.0, -1.0, 1.0])
    ours = llff_to_opencv(mats)
    np.testing.assert_allclose(ours[:, :3, :], theirs, atol=1e-12)
    np.testing.assert_allclose(opencv_to_llff(ours), mats, atol=1e-12)


def test_intrinsics_scale_each_axis(tmp_path):
    c2w = np.eye(4)
    np.save(tmp_path / "pb.npy", np.array([llff_row(c2w), llff_row(c2w)]))
    cams = read_poses_bounds(tmp_path / "pb.npy")
    assert (cams.width, cams.height, cams.focal) == (POSES_SIZE[0], POSES_SIZE[1], FOCAL)
    np.testing.assert_allclose(cams.intrinsics(POSES_SIZE), [[FOCAL, 0, 100], [0, FOCAL, 30], [0, 0, 1]])
    np.testing.assert_allclose(cams.intrinsics(IMAGE_SIZE), true_K())  # fx 72, fy 120
    assert true_K()[0, 0] == 72.0 and true_K()[1, 1] == 120.0


@pytest.mark.parametrize("damage,message", [
    (lambda a: a[:, :16], "[N, 17]"),
    (lambda a: a.reshape(-1), "[N, 17]"),
    (lambda a: np.where(np.arange(17) == 3, np.nan, a), "row 0: non-finite"),
    (lambda a: np.concatenate([a[:1], a[1:2] * np.where(np.arange(17) == 14, 1.01, 1.0)]), "row 1: [H, W, focal]"),
    (lambda a: a * np.where(np.arange(17) == 4, 0.0, 1.0), "row 0: [H, W, focal]"),
    (lambda a: a * np.where(np.arange(17) == 1, 1.5, 1.0), "not a rotation"),  # a stretched axis
    (lambda a: a * np.where(np.isin(np.arange(17), (0, 5, 10)), -1.0, 1.0), "not a rotation"),  # a reflection
])
def test_bad_poses_bounds_name_the_file_and_row(tmp_path, damage, message):
    rows = np.array([llff_row(np.eye(4)), llff_row(np.eye(4))])
    np.save(tmp_path / "pb.npy", damage(rows))
    with pytest.raises(LlffError, match="pb.npy") as e:
        read_poses_bounds(tmp_path / "pb.npy")
    assert message in str(e.value)


def test_unreadable_poses_bounds(tmp_path):
    (tmp_path / "pb.npy").write_bytes(b"not numpy")
    with pytest.raises(LlffError, match="pb.npy: not a readable"):
        read_poses_bounds(tmp_path / "pb.npy")


# ---------------------------------------------------------------------------------------------- protocol
def brute_force_inputs(centres: np.ndarray) -> list[int]:
    out = []
    for i, c in enumerate(centres):
        best, best_d = None, np.inf
        for j, d in enumerate(centres):
            dist = float(np.sqrt(((c - d) ** 2).sum()))
            if j != i and dist < best_d:
                best, best_d = j, dist
        out.append(best)
    return out


@pytest.mark.parametrize("seed", range(5))
def test_every_frame_is_one_target_of_its_nearest_other_pair(seed):
    centres = np.random.default_rng(seed).normal(size=(int(8 + 5 * seed), 3))
    expected = brute_force_inputs(centres)
    assert S.nearest_inputs(centres).tolist() == expected
    pairs = S.input_pairs(centres)
    flat = sorted(i for _, ts in pairs for i in ts)
    assert flat == list(range(len(centres)))  # each frame a target exactly once
    for j, targets in pairs:
        assert targets and j not in targets and list(targets) == sorted(targets)
        assert all(expected[i] == j for i in targets)
    assert [j for j, _ in pairs] == sorted({*expected})


def test_protocol_ties_and_degenerate_scenes():
    line = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])  # frame 1 is 1 from both 0 and 2
    assert S.nearest_inputs(line).tolist() == [1, 0, 1]
    assert S.input_pairs(line) == [(0, (1,)), (1, (0, 2))]
    assert S.input_pairs(line[:2]) == [(0, (1,)), (1, (0,))]
    same = np.zeros((3, 3))  # coinciding cameras: still never its own input
    assert S.nearest_inputs(same).tolist() == [1, 0, 0]
    with pytest.raises(ValueError, match="N >= 2"):
        S.nearest_inputs(line[:1])


def test_scale_and_rectification_measures():
    left = np.stack([np.eye(4), translation(np.array([0.0, 0.0, 2.0]))])
    right = left @ translation(np.array([0.5, 0.0, 0.0]))
    np.testing.assert_allclose(S.pair_scales(left, right, 0.12), [0.24, 0.24])
    rot, direction = S.rectification_angles(left, right)
    np.testing.assert_allclose(rot, 0.0, atol=1e-6)
    np.testing.assert_allclose(direction, 0.0, atol=1e-6)
    turned = right.copy()
    turned[1, :3, :3] = rotation_about([0, 1, 0], 5.0)
    assert S.rectification_angles(left, turned)[0][1] == pytest.approx(5.0)
    swapped = left @ translation(np.array([-0.5, 0.0, 0.0]))
    np.testing.assert_allclose(S.rectification_angles(left, swapped)[1], 180.0)
    up = left @ translation(np.array([0.5, 0.5, 0.0]))
    np.testing.assert_allclose(S.rectification_angles(left, up)[1], 45.0)
    assert np.isinf(S.pair_scales(left, left, 0.12)).all()


# ---------------------------------------------------------------------------------------------- the import
def test_import_recovers_the_known_cameras_and_images(stereonvs_scenes, stereonvs_dataset):
    found = samples(stereonvs_dataset)
    report = json.loads((stereonvs_dataset / S.REPORT_NAME).read_text())
    targets_seen = {}
    for scene in stereonvs_scenes:
        name = scene.folder.name
        row = next(r for r in report["scenes"] if r["scene"] == name)
        assert row["scale_m_per_unit"] == pytest.approx(1.0 / scene.scale, rel=1e-9)  # COLMAP units are s x metres
        # The imported world is the COLMAP one brought to metres: x = R x_true + t / s.
        expected = scene.to_colmap(scene.c2w_left)
        expected[:, :3, 3] /= scene.scale
        pairs = S.input_pairs(scene.c2w_left[:, :3, 3])
        assert row["pairs"] == len(pairs) and row["targets"] == len(scene.names) == 7
        for j, targets in pairs:
            meta, members = found[f"{name}__{j:06d}"]
            np.testing.assert_allclose(meta.K, true_K(), atol=1e-9)
            assert (meta.width, meta.height) == IMAGE_SIZE and meta.baseline == BASELINE
            assert meta.subset == "StereoNVS" and meta.teacher_psnr is None
            np.testing.assert_allclose(meta.c2w_left, expected[j], atol=1e-9)
            np.testing.assert_allclose(meta.c2w_right, expected[j] @ translation(np.array([BASELINE, 0, 0])),
                                       atol=1e-9)
            assert meta.target_frames == targets and meta.target_ids == tuple(range(len(targets)))
            np.testing.assert_allclose(meta.targets, expected[list(targets)], atol=1e-9)
            # What the model consumes: target poses relative to the left camera, in metres.
            rel = np.linalg.inv(meta.targets) @ meta.c2w_left
            np.testing.assert_allclose(rel, np.linalg.inv(scene.c2w_left[list(targets)]) @ scene.c2w_left[j], atol=1e-9)
            dist = np.linalg.norm(scene.c2w_left[list(targets), :3, 3] - scene.c2w_left[j, :3, 3], axis=1)
            assert meta.rho == pytest.approx(dist.max())
            files = [scene.folder / "images/left" / scene.names[j], scene.folder / "images/right" / scene.names[j]]
            files += [scene.folder / "images/left" / scene.names[i] for i in targets]
            names = ["left.jpg", "right.jpg"] + [f"target_{k:02d}.jpg" for k in range(len(targets))]
            for file, member in zip(files, names):
                if scene.suffix == ".jpg":
                    assert members[member] == file.read_bytes()  # JPEGs byte for byte
                else:
                    source = decode_image(file.read_bytes(), "png")
                    assert psnr(decode_image(members[member], "jpg"), source) > 35  # PNGs re-encoded at q92
            for k in range(len(targets)):
                assert (decode_image(members[f"mask_{k:02d}.png"], "png") == 255).all()
            targets_seen.update({(name, i): j for i in targets})
        assert sorted(i for (n, i) in targets_seen if n == name) == list(range(7))
    stats = json.loads((stereonvs_dataset / "stats.json").read_text())
    assert stats["subsets"]["StereoNVS"]["splits"]["test"] == {"scenes": 2, "pairs": len(found), "targets": 14,
                                                                "teacher_psnr": None}
    bench = json.loads((stereonvs_dataset / "benchmark.json").read_text())
    assert bench["masked"] is False and bench["source"] == "captured"
    office_pairs = S.input_pairs(stereonvs_scenes[1].c2w_left[:, :3, 3])
    assert report["reencoded_images"] == 2 * len(office_pairs) + 7  # every stored image of the PNG scene


def test_imported_cameras_reproduce_the_images(stereonvs_scenes, stereonvs_dataset):
    """Render the room at each imported target camera (brought back to the room's frame through the left
    camera) with the imported K: the stored target must match, so axes, scale, K and the target choice are
    all right."""
    scene = stereonvs_scenes[0]
    room = make_room(1, sh_degree=1, num_gaussians=3000)
    for key, (meta, members) in samples(stereonvs_dataset).items():
        if meta.scene != "lab":
            continue
        true_left = scene.c2w_left[meta.frame]
        cams = true_left @ np.linalg.inv(meta.c2w_left) @ meta.targets
        images = render(room, cams, meta.K)
        for k, image in enumerate(images):
            assert psnr(image, decode_image(members[f"target_{k:02d}.jpg"], "jpg")) > 35, key
        assert psnr(render(room, true_left[None], meta.K)[0], decode_image(members["left.jpg"], "jpg")) > 35


def test_inspect_accepts_the_import(stereonvs_dataset, tmp_path):
    report = inspect_dataset(stereonvs_dataset, contact_sheet=tmp_path / "sheet.png")
    assert not report.problems


def test_eval_batches_group_samples_by_target_count(stereonvs_dataset):
    counts = [m.num_targets for m, _ in samples(stereonvs_dataset).values()]
    assert len(set(counts)) > 1  # the fixture has pairs with 1 and with 2 targets
    batches = list(eval_batches(stereonvs_dataset, "test", batch_size=3, resolution=32))
    assert sum(b["targets"].shape[0] for b in batches) == len(counts)
    assert sum(b["targets"].shape[0] * b["targets"].shape[1] for b in batches) == 14
    for b in batches:
        assert b["targets"].shape[0] <= 3 and b["masks"].all()
        assert b["targets"].shape[-2:] == (32, 32) and torch.isfinite(b["target_viewmats"]).all()


# ---------------------------------------------------------------------------------------------- refusals
def copy_root(stereonvs_scenes, tmp_path):
    root = tmp_path / "root"
    shutil.copytree(stereonvs_scenes[0].folder.parent, root)
    return root


def rewrite_poses(root, scene, change):
    path = root / scene / "poses_bounds.npy"
    np.save(path, change(np.load(path)))


def scaled_right(rows, pair, factor):
    """Move the right camera of ``pair`` so that its baseline is ``factor`` times longer."""
    n = len(rows) // 2
    rows = rows.copy()
    left, right = rows[pair, [3, 8, 13]], rows[n + pair, [3, 8, 13]]
    rows[n + pair, [3, 8, 13]] = left + factor * (right - left)
    return rows


@pytest.mark.parametrize("change,message", [
    (lambda root: rewrite_poses(root, "lab", lambda r: scaled_right(r, 3, 1.2)),
     "pair 3 (001021.jpg): its baseline gives"),
    (lambda root: rewrite_poses(root, "lab", lambda r: np.concatenate([r[7:], r[:7]])),  # left and right swapped
     "baseline is 180.00 deg off"),
    (lambda root: rewrite_poses(root, "office", lambda r: r[:-2]), "12 rows for 7 stereo pairs"),
    (lambda root: (root / "lab/images/right/001042.jpg").rename(root / "lab/images/right/zzz.jpg"),
     "left and right differ at image 6"),
    (lambda root: (root / "lab/images/right/001042.jpg").unlink(), "7 left and 6 right images"),
    (lambda root: (root / "office/images/left/001000.png").write_bytes(b"broken"), "001000.png"),
    (lambda root: shutil.rmtree(root / "office/images/right"), "office/images/right: missing"),
    (lambda root: (root / "lab/images/right/001007.jpg").write_bytes(encode_jpeg(np.zeros((40, 96, 3), np.uint8))),
     "001007.jpg: 96x40 pixels, 001000.jpg has 96x48"),
])
def test_a_refused_import_names_the_problem_and_leaves_out_alone(stereonvs_scenes, tmp_path, capsys, change,
                                                                 message):
    root = copy_root(stereonvs_scenes, tmp_path)
    change(root)
    out = tmp_path / "out"
    (out / "test").mkdir(parents=True)
    (out / "test" / "keep.txt").write_text("earlier")
    write_manifest(out, S.OWNER)  # an earlier import's
    assert cli_main(["import", "stereonvs", str(root), "--out", str(out), "--baseline", "0.12", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in out.rglob("*")) == [".written-by", "keep.txt", "test"]


def turned_right(rows, pair, degrees):
    """Turn the right camera of ``pair`` by ``degrees`` about the world's y axis (about its own centre)."""
    n = len(rows) // 2
    rows = rows.copy()
    m = rows[n + pair, :15].reshape(3, 5)
    m[:, :3] = rotation_about([0, 1, 0], degrees) @ m[:, :3]
    rows[n + pair, :15] = m.reshape(-1)
    return rows


def test_scale_and_rectification_tolerances_are_flags(stereonvs_scenes, tmp_path):
    root = copy_root(stereonvs_scenes, tmp_path)
    rewrite_poses(root, "lab", lambda r: turned_right(scaled_right(r, 3, 1.04), 2, 0.5))
    report = S.import_stereonvs(root, tmp_path / "a", BASELINE, scenes=["lab"], progress=False)  # defaults: 5%, 3 deg
    row = report["scenes"][0]
    assert row["scale_spread"] == pytest.approx(1 - 1 / 1.04) and row["max_rotation_deg"] == pytest.approx(0.5)
    with pytest.raises(S.StereoNvsError, match=r"pair 3 .*3\.8% off .*--scale-tolerance 0.01"):
        S.import_stereonvs(root, tmp_path / "b", BASELINE, scenes=["lab"], scale_tolerance=0.01, progress=False)
    with pytest.raises(S.StereoNvsError, match=r"pair 2 .*0\.50 deg apart.*--rectification-tolerance 0.1 deg"):
        S.import_stereonvs(root, tmp_path / "c", BASELINE, scenes=["lab"], rectification_tolerance=0.1,
                           progress=False)
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


def test_one_pair_scenes_and_unknown_scenes_are_refused(stereonvs_scenes, tmp_path):
    root = copy_root(stereonvs_scenes, tmp_path)
    with pytest.raises(S.StereoNvsError, match="not found"):
        S.import_stereonvs(root, tmp_path / "o", BASELINE, scenes=["kitchen"], progress=False)
    for side in ("left", "right"):
        for f in sorted((root / "lab/images" / side).iterdir())[1:]:
            f.unlink()
    rewrite_poses(root, "lab", lambda r: r[[0, 7]])
    with pytest.raises(S.StereoNvsError, match="one stereo pair"):
        S.import_stereonvs(root, tmp_path / "o", BASELINE, scenes=["lab"], progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(S.StereoNvsError, match="no scene folder"):
        S.import_stereonvs(tmp_path / "empty", tmp_path / "o", BASELINE, progress=False)
    with pytest.raises(S.StereoNvsError, match="--baseline 0"):
        S.import_stereonvs(root, tmp_path / "o", 0.0, progress=False)
    assert not (tmp_path / "o").exists()


def test_an_import_never_replaces_a_build(stereonvs_scenes, replicags_dataset, tmp_path):
    out = tmp_path / "build"
    shutil.copytree(replicags_dataset, out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match="holds files not written by `scenesplat-stereo import stereonvs`"):
        S.import_stereonvs(stereonvs_scenes[0].folder.parent, out, BASELINE, progress=False)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_cli_import_prints_the_table_and_replaces_an_earlier_import(stereonvs_scenes, tmp_path, capsys):
    root = copy_root(stereonvs_scenes, tmp_path)
    out = tmp_path / "out"
    argv = ["import", "stereonvs", str(root), "--out", str(out), "--baseline", "0.12", "--no-progress",
            "--samples-per-shard", "2"]
    assert cli_main(argv) == 0
    text = capsys.readouterr().out
    assert "total 2" in text and "8 scenes, 224" in text and "72.0  120.0" in text
    assert len(list((out / "test").glob("shard-*.tar"))) == 5  # 9 samples, 2 per shard
    assert cli_main(argv[:-1] + ["8", "--scenes", "lab"]) == 0
    assert len(list((out / "test").glob("shard-*.tar"))) == 1  # the earlier shards are gone
    assert {m.scene for m, _ in samples(out).values()} == {"lab"}
