"""pipelines/irs_targets.py: each target-selection rule of SPEC section 6 / paper appendix F, and the
shards written from a synthetic IRS-like variant (ground-truth poses, no COLMAP needed)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipelines import irs_targets as T
from tests.support.irs_synthetic import cached_variant

NO_COVERAGE = T.TargetRules(min_coverage=0.0)  # isolates the distance and rotation rules


def _pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """c2w with the camera turned by ``yaw_deg`` about its y axis, centre (x, y, z)."""
    a = math.radians(yaw_deg)
    c2w = np.eye(4)
    c2w[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    c2w[:3, 3] = [x, y, z]
    return c2w


def test_constants_are_the_papers():
    r = T.TargetRules()
    assert (r.reference_min_translation, r.reference_min_rotation_deg) == (0.05, 5.0)
    assert (r.min_distance, r.max_distance, r.max_rotation_deg) == (0.03, 0.40, 30.0)
    assert (r.min_coverage, r.coverage_goal, r.max_targets) == (0.4, 0.8, 8)
    assert (T.TRAIN_MIN_TARGETS, T.VAL_VARIANTS) == (4, 8)


def test_rotation_angle():
    assert T.rotation_angle_deg(_pose(), _pose(yaw_deg=30.0)) == pytest.approx(30.0)
    assert T.rotation_angle_deg(_pose(yaw_deg=-10), _pose(yaw_deg=25)) == pytest.approx(35.0)
    many = T.rotation_angle_deg(_pose(), np.stack([_pose(yaw_deg=a) for a in (0.0, 90.0, 180.0)]))
    np.testing.assert_allclose(many, [0.0, 90.0, 180.0], atol=1e-6)


def test_reference_frames_by_translation_increment():
    xs = [0.0, 0.02, 0.04, 0.05, 0.07, 0.09, 0.101, 0.12]  # 0.05 exactly from frame 0: inclusive
    assert T.select_references(np.stack([_pose(x) for x in xs])) == [0, 3, 6]


def test_reference_frames_by_rotation_increment_or_translation():
    yaws = [0.0, 2.0, 4.0, 5.01, 9.0, 10.5, 10.2]
    assert T.select_references(np.stack([_pose(yaw_deg=a) for a in yaws])) == [0, 3, 5]
    # Either increment suffices: a small move with a large turn, a large move with no turn.
    poses = np.stack([_pose(), _pose(0.01, yaw_deg=6.0), _pose(0.07, yaw_deg=6.0), _pose(0.08, yaw_deg=7.0)])
    assert T.select_references(poses) == [0, 1, 2]
    assert T.select_references(np.zeros((0, 4, 4))) == []
    # Inclusive bound, at an angle arccos returns exactly (180 deg).
    half_turn = T.TargetRules(reference_min_rotation_deg=180.0)
    assert T.select_references(np.stack([_pose(), _pose(yaw_deg=180.0)]), half_turn) == [0, 1]


def test_depth_points_pixel_centres_and_invalid_depth():
    K = np.array([[10.0, 0, 2.0], [0, 10.0, 1.5], [0, 0, 1]])
    depth = np.full((3, 4), 2.0)
    depth[0, 1], depth[2, 3] = np.nan, 0.0
    c2w = _pose(1.0, 2.0, 3.0)
    pts = T.depth_points(depth, K, c2w)
    assert len(pts) == 10
    cam = pts - c2w[:3, 3]
    np.testing.assert_allclose(cam[:, 2], 2.0)
    u, v = 10 * cam[:, 0] / 2 + 2.0, 10 * cam[:, 1] / 2 + 1.5
    grid = {(float(a), float(b)) for a, b in zip(u.round(9), v.round(9))}
    assert (0.5, 0.5) in grid and (1.5, 0.5) not in grid and (3.5, 2.5) not in grid and (3.5, 1.5) in grid
    strided = T.depth_points(depth, K, c2w, stride=2)  # pixels (0,0), (0,2), (2,0), (2,2) (row, col)
    assert len(strided) == 4


def test_frustum_coverage_in_front_and_inside_half_open_image():
    K = np.array([[8.0, 0, 2.0], [0, 8.0, 1.5], [0, 0, 1]])  # a 4 x 3 image
    pts = np.array([
        [0, 0, 1],          # centre: inside
        [0, 0, -1],         # behind
        [-0.25, 0, 1],      # u = 0: inside (pixel 0 covers [0, 1))
        [0.25, 0, 1],       # u = 4 = W: outside
        [0, 0.1875, 1],     # v = 3 = H: outside
        [0, -0.1875, 1],    # v = 0: inside
        [10, 0, 1],         # far right
        [0, 0, 0],          # on the camera plane: not in front
    ], dtype=np.float64)
    assert T.frustum_coverage(pts, np.eye(4), K, 4, 3) == 3 / 8
    moved = _pose(z=5.0)  # the world-to-camera transform is applied
    assert T.frustum_coverage(pts + [0, 0, 5.0], moved, K, 4, 3) == 3 / 8
    assert T.frustum_coverage(np.zeros((0, 3)), np.eye(4), K, 4, 3) == 0.0


def test_frustum_coverage_of_a_wall_seen_from_a_side_step():
    # 40 x 10 image, fx = 20: a wall at z = 2 spans x in [-2, 2); its points sit at x = -1.95 ... 1.95.
    # A target 0.3 m to the right sees x in [-1.7, 2.3): 37 of the 40 columns.
    K = np.array([[20.0, 0, 20.0], [0, 20.0, 5.0], [0, 0, 1]])
    pts = T.depth_points(np.full((10, 40), 2.0), K, np.eye(4))
    assert T.frustum_coverage(pts, _pose(0.3), K, 40, 10) == pytest.approx(37 / 40)
    assert T.frustum_coverage(pts, _pose(), K, 40, 10) == 1.0


def _far_wall(K: np.ndarray) -> np.ndarray:
    return T.depth_points(np.full((10, 40), 50.0), K, np.eye(4))


def test_target_distance_bounds_inclusive():
    K = np.array([[20.0, 0, 20.0], [0, 20.0, 5.0], [0, 0, 1]])
    xs = [0.0, 0.02, 0.03, 0.2, 0.4, 0.41]
    c2w = np.stack([_pose(x) for x in xs])
    got = T.select_targets(0, c2w, _far_wall(K), K, 40, 10, NO_COVERAGE)
    assert sorted(t.index for t in got) == [2, 3, 4]
    assert {t.index: t.distance for t in got} == pytest.approx({2: 0.03, 3: 0.2, 4: 0.4})


def test_target_rotation_bound_and_reference_excluded():
    K = np.array([[20.0, 0, 20.0], [0, 20.0, 5.0], [0, 0, 1]])
    c2w = np.stack([_pose(), _pose(0.1, yaw_deg=29.9), _pose(0.1, yaw_deg=30.1), _pose(-0.1, yaw_deg=-29.9),
                    _pose(0.0, 0.1, yaw_deg=-31.0)])
    got = T.select_targets(0, c2w, _far_wall(K), K, 40, 10, NO_COVERAGE)
    assert sorted(t.index for t in got) == [1, 3]
    anywhere = T.TargetRules(min_distance=0.0, max_rotation_deg=180.0, min_coverage=0.0)
    assert 0 not in [t.index for t in T.select_targets(0, c2w, _far_wall(K), K, 40, 10, anywhere)]


def test_target_coverage_threshold_ranking_ties_and_cap(monkeypatch):
    coverage = {1: 0.39, 2: 0.4, 3: 0.8, 4: 0.85, 5: 0.7, 6: 0.7, 7: 0.95, 8: 0.6, 9: 0.5, 10: 0.45, 11: 0.99}
    c2w = np.stack([_pose()] + [_pose(0.1, z=0.001 * j) for j in coverage])
    monkeypatch.setattr(T, "frustum_coverage", lambda pts, pose, K, w, h: coverage[round(pose[2, 3] * 1000)])
    K = np.eye(3)
    got = T.select_targets(0, c2w, np.zeros((1, 3)), K, 4, 3)
    # |c - 0.8|: 3 -> 0, 4 -> .05, 5 = 6 -> .1 (tie: lower index), 7 -> .15, 11 -> .19, 8 -> .2, 9 -> .3, then
    # 10 -> .35 and 2 -> .4 (0.4 is kept) are cut by the cap of 8; 1 (0.39) is never a candidate.
    assert [t.index for t in got] == [3, 4, 5, 6, 7, 11, 8, 9]
    assert [t.coverage for t in got] == [coverage[t.index] for t in got]
    everything = T.select_targets(0, c2w, np.zeros((1, 3)), K, 4, 3, T.TargetRules(max_targets=100))
    assert [t.index for t in everything][-2:] == [10, 2] and 1 not in [t.index for t in everything]


def test_split_samples_train_minimum_and_validation_pairs():
    counts = [0, 3, 4, 8, 5, 4, 6, 4, 7, 9]
    refs = [T.Reference(i, [T.Target(100 + k, 0.1, 1.0, 0.8) for k in range(n)]) for i, n in enumerate(counts)]
    assert [r.index for r in T.split_samples(refs, "train")] == [2, 3, 4, 5, 6, 7, 8, 9]
    assert [r.index for r in T.split_samples(refs, "train", min_targets=1)] == [1, 2, 3, 4, 5, 6, 7, 8, 9]
    val = T.split_samples(refs, "val")
    # The 8 references with >= 4 targets; numpy.linspace(0, 7, 5).round() = [0, 2, 4, 5, 7] among them.
    assert [r.index for r in val] == [2, 4, 6, 7, 9]
    assert all([t.index for t in r.targets] == [100, 101, 102, 103] for r in val)
    with pytest.raises(ValueError, match="split"):
        T.split_samples(refs, "test")


# ------------------------------------------------------------------------------------------ shards
def _poses_dir(variant, root: Path) -> Path:
    """A pose-recovery output with the ground-truth poses: two kept variants (same images) and a rejected
    one."""
    trans = np.eye(4)
    trans[0, 3] = 0.1
    frames = [{"frame": n, "left": f"l_{n}.png", "right": f"r_{n}.png", "disparity": f"d_{n}.exr",
               "c2w_left": c.tolist(), "c2w_right": (c @ trans).tolist()}
              for n, c in enumerate(variant.c2w, start=1)]
    for name, kept in (("Home-Synth", True), ("Home-Synth2", True), ("Home-Bad", False)):
        (root / name).mkdir(parents=True)
        doc = {"variant": name, "source": str(variant.folder), "width": 240, "height": 135,
               "K": variant.camera.K.tolist(), "baseline": 0.1, "scale": 1.0, "frames": frames}
        (root / name / "poses.json").write_text(json.dumps(doc))
        (root / name / "report.json").write_text(json.dumps({"variant": name, "kept": kept}))
    (root / "Home-NoReport").mkdir()
    return root


def test_shards_from_synthetic_variant(tmp_path_factory, tmp_path, capsys):
    from scenesplat_stereo.shards.encode import decode_image
    from scenesplat_stereo.shards.webdataset import iter_shard

    variant = cached_variant(tmp_path_factory.getbasetemp())
    poses = _poses_dir(variant, tmp_path / "poses")
    assert T.kept_variants(poses) == ["Home-Synth", "Home-Synth2"]
    out = tmp_path / "shards"
    args = [str(poses), "--out", str(out), "--val-variants", "1", "--depth-stride", "2", "--samples-per-shard",
            "16", "--no-progress"]
    assert T.main(args) == 0
    table = capsys.readouterr().out
    selection = json.loads((out / "irs_selection.json").read_text())
    rows = {r["variant"]: r for r in selection["variants"]}
    assert sorted(r["split"] for r in rows.values()) == ["train", "val"]
    gt = {n: c for n, c in enumerate(variant.c2w, start=1)}
    left_png = {}
    seen = {"train": 0, "val": 0}
    for split in ("train", "val"):
        index = json.loads((out / split / "index.json").read_text())
        name = next(n for n, r in rows.items() if r["split"] == split)
        assert index["num_samples"] == rows[name]["pairs"] > 0
        for shard in index["shards"]:
            for key, members in iter_shard(out / split / shard["name"]):
                meta = json.loads(members["json"])
                n_t = len(meta["targets"])
                assert key == f"{name}__{meta['frame']:06d}" and meta["scene"] == name and meta["subset"] == "IRS"
                assert set(members) == {"left.jpg", "right.jpg", "json"} | {
                    f"{kind}_{j:02d}.{ext}" for j in range(n_t) for kind, ext in (("target", "jpg"), ("mask", "png"))}
                assert (n_t == 4) if split == "val" else (4 <= n_t <= 8)
                assert meta["target_ids"] == list(range(n_t)) and meta["teacher_psnr"] is None
                assert meta["K"] == variant.camera.K.tolist() and meta["baseline"] == 0.1
                np.testing.assert_allclose(meta["c2w_left"], gt[meta["frame"]], atol=1e-12)
                np.testing.assert_allclose(meta["targets"], [gt[f] for f in meta["target_frames"]], atol=1e-12)
                # Every target obeys the rules; ranked by |coverage - 0.8|.
                c_ref = np.array(meta["c2w_left"])
                dist = [np.linalg.norm(np.array(t)[:3, 3] - c_ref[:3, 3]) for t in meta["targets"]]
                assert all(0.03 <= d <= 0.40 for d in dist) and meta["rho"] == pytest.approx(max(dist))
                assert all(T.rotation_angle_deg(c_ref, np.array(t)) <= 30 for t in meta["targets"])
                cov = meta["target_coverage"]
                assert min(cov) >= 0.4 and [abs(c - 0.8) for c in cov] == sorted(abs(c - 0.8) for c in cov)
                for j in range(n_t):
                    mask = decode_image(members[f"mask_{j:02d}.png"], "png")
                    assert mask.shape == (135, 240, 1) and (mask == 255).all()
                if not left_png:  # JPEG of the IRS PNG, quality 92: close to the source pixels
                    left_png = {"jpg": decode_image(members["left.jpg"], "jpg"),
                                "png": T.read_rgb(variant.folder / f"l_{meta['frame']}.png")}
                seen[split] += 1
    train_rows = [r for r in rows.values() if r["split"] == "train"]
    assert seen["val"] == 5 and seen["train"] == train_rows[0]["pairs"]
    diff = np.abs(left_png["jpg"].astype(int) - left_png["png"].astype(int))
    assert left_png["jpg"].shape == (135, 240, 3) and diff.mean() < 3
    stats = json.loads((out / "stats.json").read_text())
    assert stats["subsets"]["IRS"]["splits"]["val"]["pairs"] == 5
    assert stats["subsets"]["IRS"]["splits"]["val"]["targets"] == 20
    assert "total 1" in table and "Home-Synth" in table
    # Deterministic: the same inputs give the same bytes.
    again = tmp_path / "again"
    assert T.main([str(poses), "--out", str(again)] + args[3:]) == 0
    for tar in sorted(out.glob("*/shard-*.tar")):
        assert tar.read_bytes() == (again / tar.parent.name / tar.name).read_bytes()


def test_shards_need_a_kept_variant(tmp_path, capsys):
    (tmp_path / "poses" / "V").mkdir(parents=True)
    (tmp_path / "poses" / "V" / "report.json").write_text('{"kept": false}')
    assert T.main([str(tmp_path / "poses"), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "no kept variant" in capsys.readouterr().err
