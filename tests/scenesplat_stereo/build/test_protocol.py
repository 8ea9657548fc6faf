"""The SceneSplat-Stereo protocol (SPEC section 4) against the paper's numbers (appendix B, Table 6/7)."""

from __future__ import annotations

import dataclasses
import math
import random
from pathlib import Path

import numpy as np
import pytest

import scenesplat_stereo.build.protocol as protocol
from scenesplat_stereo.build.protocol import (MASK_ALPHA_THRESHOLD, MIN_TEACHER_PSNR, NUM_TARGETS, TIERS, VAL_SCENES,
                                              VAL_TARGETS, filter_teachers, keep_teacher, plan_scene, split_scenes,
                                              tier_for_psnr, validation_frames)
from scenesplat_stereo.scene.cameras import intrinsics_matrix, look_at
from scenesplat_stereo.scene.teachers import OrbitSpec, Teacher
from scenesplat_stereo.shards.sample import JPEG_QUALITY


def make_teacher(n_frames: int = 20, psnr: float | None = 33.0, scene_id: str = "scene0000_00",
                 subset: str = "ScanNetGS", width: int = 64, height: int = 48) -> Teacher:
    eyes = np.column_stack([np.linspace(0, 2, n_frames), np.zeros(n_frames), np.zeros(n_frames)])
    c2w = look_at(eyes, eyes + np.array([0.0, 0.0, 1.0]))
    K = intrinsics_matrix(50.0, 50.0, width / 2, height / 2)
    return Teacher(scene_id=scene_id, subset=subset, layout="plain", ply_path=Path("/nonexistent.ply"),
                   psnr=psnr, c2w=c2w, Ks=np.repeat(K[None], n_frames, 0), width=width, height=height,
                   sh_degree=0, camera_convention="opencv", frame_names=[f"f{i}" for i in range(n_frames)])


def test_constants_from_paper():
    assert MIN_TEACHER_PSNR == 30.0 and NUM_TARGETS == 10 and VAL_TARGETS == (0, 1, 2, 3)
    assert JPEG_QUALITY == 92 and MASK_ALPHA_THRESHOLD == 0.5
    assert VAL_SCENES == {"ScanNetGS": 30, "ScanNetPPGS-V2": 20}
    # Paper Table 7: (30,35) -> 0.05/0.10, [35,40) -> 0.10/0.20, [40,inf) -> 0.10/0.30
    assert [(t.psnr_low, t.psnr_high, t.baseline, t.rho) for t in TIERS] == [
        (30.0, 35.0, 0.05, 0.10), (35.0, 40.0, 0.10, 0.20), (40.0, math.inf, 0.10, 0.30)]


@pytest.mark.parametrize("psnr,tier", [(30.0001, 0), (31.69, 0), (34.9999, 0), (35.0, 1), (39.999, 1),
                                       (40.0, 2), (41.21, 2), (1e6, 2), (math.inf, 2)])
def test_tier_boundaries(psnr, tier):
    assert tier_for_psnr(psnr) == TIERS[tier]
    ratio = tier_for_psnr(psnr).rho / tier_for_psnr(psnr).baseline
    assert ratio == pytest.approx(2.0) or ratio == pytest.approx(3.0)  # "two to three times"


@pytest.mark.parametrize("psnr", [30.0, 29.99, 0.0, -5.0, None, math.nan])
def test_no_tier_at_or_below_30(psnr):
    with pytest.raises(ValueError, match="no quality tier"):
        tier_for_psnr(psnr)


def test_keep_teacher_strictly_above():
    assert not keep_teacher(30.0)
    assert keep_teacher(30.000001)
    assert not keep_teacher(None)
    assert not keep_teacher(math.nan)
    assert keep_teacher(None, None) and keep_teacher(12.0, None)
    assert keep_teacher(25.5, 25.0) and not keep_teacher(25.0, 25.0)


def test_filter_teachers_reasons():
    ts = [make_teacher(psnr=p, scene_id=f"s{i}") for i, p in enumerate([31.0, 30.0, None, 45.0])]
    kept, dropped = filter_teachers(ts)
    assert [t.scene_id for t in kept] == ["s0", "s3"]
    assert [r.scene_id for r in dropped] == ["s1", "s2"]
    assert "PSNR 30.00 dB not above 30.0" in dropped[0].reason
    assert "no PSNR" in dropped[1].reason and dropped[1].subset == "ScanNetGS"
    kept, dropped = filter_teachers(ts, None)
    assert len(kept) == 4 and not dropped


def test_split_sizes_of_the_paper():
    gs = [f"scene{i:04d}_00" for i in range(521)]
    pp = [f"{i:010x}" for i in range(332)]
    random.Random(7).shuffle(gs)  # input order must not matter
    splits = split_scenes({"ScanNetGS": gs, "ScanNetPPGS-V2": pp})
    val_gs = [s for s in gs if splits[s] == "val"]
    val_pp = [s for s in pp if splits[s] == "val"]
    assert (len(val_gs), len(gs) - len(val_gs)) == (30, 491)
    assert (len(val_pp), len(pp) - len(val_pp)) == (20, 312)
    assert sum(v == "train" for v in splits.values()) == 803  # paper: 803 training / 50 validation
    # SPEC: random.Random(42).sample(sorted(ids), k), a fresh generator per subset
    assert set(val_gs) == set(random.Random(42).sample(sorted(gs), 30))
    assert set(val_pp) == set(random.Random(42).sample(sorted(pp), 20))
    # one subset's split does not depend on the others
    alone = split_scenes({"ScanNetPPGS-V2": pp})
    assert {s for s in pp if alone[s] == "val"} == set(val_pp)


def test_split_counts_override_and_errors():
    ids = {"default": ["a", "b", "c", "d"], "ReplicaGS": ["r1", "r2"]}
    assert set(split_scenes(ids).values()) == {"train"}  # subsets VAL_SCENES does not name: no val
    s = split_scenes(ids, {"default": 2})
    assert sum(v == "val" for v in s.values()) == 2
    assert s == split_scenes(ids, {"default": 2})  # deterministic
    other = {i for i, v in split_scenes(ids, {"default": 2}, seed=1).items() if v == "val"}
    assert other == set(random.Random(1).sample(["a", "b", "c", "d"], 2))
    with pytest.raises(ValueError, match="cannot hold out 5"):
        split_scenes(ids, {"default": 5})
    with pytest.raises(ValueError, match="more than once"):
        split_scenes({"x": ["a"], "y": ["a"]})


@pytest.mark.parametrize("n,expected", [
    (100, [0, 25, 50, 74, 99]),  # linspace 0, 24.75, 49.5, 74.25, 99 (numpy rounds half to even)
    (6, [0, 1, 2, 4, 5]),  # 0, 1.25, 2.5, 3.75, 5
    (9, [0, 2, 4, 6, 8]),
    (5, [0, 1, 2, 3, 4]),
    (3, [0, 1, 2]),  # no more frames than asked: each frame once
    (1, [0]),
    (0, []),
])
def test_validation_frames(n, expected):
    assert validation_frames(n) == expected


def test_test_frames():
    frames = protocol.test_frames(2000)  # ReplicaGS: 2000-frame trajectories -> 100 pairs
    assert len(frames) == 100 and len(set(frames)) == 100 and frames == sorted(frames)
    assert frames[0] == 0 and frames[-1] == 1999
    assert frames == [int(v) for v in np.linspace(0, 1999, 100).round()]
    assert protocol.test_frames(100) == list(range(100))
    assert protocol.test_frames(37) == list(range(37))
    assert protocol.test_frames(101)[:3] == [0, 1, 2]


def test_validation_totals_of_the_paper():
    # 50 held-out scenes x 5 pairs x 4 targets = 250 pairs, 1000 targets (Table 6)
    plans = [p for i in range(50) for p in plan_scene(make_teacher(n_frames=300 + i, scene_id=f"v{i}"), "val")]
    assert len(plans) == 250 and sum(len(p.target_ids) for p in plans) == 1000
    assert all(p.target_ids == (0, 1, 2, 3) and p.c2w_targets.shape == (4, 4, 4) for p in plans)
    # ReplicaGS: 8 scenes x 100 pairs x 10 targets = 800 pairs, 8000 targets
    plans = [p for i in range(8) for p in plan_scene(make_teacher(n_frames=2000, psnr=41.2, scene_id=f"r{i}"), "test")]
    assert len(plans) == 800 and sum(len(p.target_ids) for p in plans) == 8000


def test_plan_scene_geometry_and_fields():
    t = make_teacher(n_frames=7, psnr=36.0)
    plans = plan_scene(t, "train")
    assert [p.frame for p in plans] == list(range(7))  # every frame, in order
    assert [p.key for p in plans][:2] == ["scene0000_00__000000", "scene0000_00__000001"]
    golden = math.pi * (3 - math.sqrt(5))
    for p in plans:
        assert (p.baseline, p.rho, p.teacher_psnr, p.split) == (0.10, 0.20, 36.0, "train")
        assert p.target_ids == tuple(range(10)) and p.c2w_targets.shape == (10, 4, 4)
        L = t.c2w[p.frame]
        np.testing.assert_array_equal(p.c2w_left, L)
        np.testing.assert_allclose(p.c2w_right[:3, 3], L[:3, 3] + 0.10 * L[:3, 0])
        for j in range(10):
            y = 1 - 2 * (j + 0.5) / 10
            u = np.array([math.sqrt(1 - y * y) * math.cos(j * golden), y, math.sqrt(1 - y * y) * math.sin(j * golden)])
            np.testing.assert_allclose(p.c2w_targets[j][:3, 3], L[:3, 3] + 0.20 * L[:3, :3] @ u, atol=1e-12)
            np.testing.assert_array_equal(p.c2w_targets[j][:3, :3], L[:3, :3])
        np.testing.assert_array_equal(p.K, t.Ks[p.frame])
        assert (p.width, p.height) == (64, 48)


def test_plan_scene_overrides():
    t = make_teacher(n_frames=4, psnr=31.0)
    p = plan_scene(t, "test", baseline=0.5, rho=2.0, num_targets=3, resolution=(128, 24))[0]
    assert (p.baseline, p.rho, p.target_ids) == (0.5, 2.0, (0, 1, 2))
    assert (p.width, p.height) == (128, 24)
    np.testing.assert_allclose(p.K, [[100, 0, 64], [0, 25, 12], [0, 0, 1]])
    np.testing.assert_allclose(np.linalg.norm(p.c2w_targets[:, :3, 3] - p.c2w_left[:3, 3], axis=1), 2.0)
    p = plan_scene(t, "train", baseline=0.2)[0]  # rho still from the tier
    assert (p.baseline, p.rho) == (0.2, 0.10)
    assert plan_scene(t, "val", num_targets=2)[0].target_ids == (0, 1)
    for bad in (0, 11):
        with pytest.raises(ValueError, match="num_targets"):
            plan_scene(t, "train", num_targets=bad)
    with pytest.raises(ValueError, match="split"):
        plan_scene(t, "validation")


def test_plan_scene_without_tier_warns_and_uses_first_tier():
    t = make_teacher(n_frames=2, psnr=None)
    with pytest.warns(UserWarning, match="no quality tier"):
        p = plan_scene(t, "train")[0]
    assert (p.baseline, p.rho, p.teacher_psnr) == (0.05, 0.10, None)
    p = plan_scene(t, "train", baseline=0.3, rho=0.6)[0]  # both given: no tier needed, no warning
    assert (p.baseline, p.rho) == (0.3, 0.6)


def test_plan_scene_takes_the_teachers_own_baseline_and_rho_before_the_tier():
    """scene.json ``baseline``/``rho`` (Teacher fields) replace the tier's; the build's flags replace both."""
    t = dataclasses.replace(make_teacher(n_frames=2, psnr=41.0), baseline=0.063, rho=0.04)
    p = plan_scene(t, "train")[0]
    assert (p.baseline, p.rho) == (0.063, 0.04)
    np.testing.assert_allclose(np.linalg.norm(p.c2w_right[:3, 3] - p.c2w_left[:3, 3]), 0.063, rtol=1e-12)
    assert (plan_scene(t, "train", baseline=0.2)[0].baseline, plan_scene(t, "train", rho=0.5)[0].rho) == (0.2, 0.5)
    half = dataclasses.replace(make_teacher(n_frames=2, psnr=41.0), baseline=0.063)   # rho from the tier (0.30)
    assert (plan_scene(half, "train")[0].baseline, plan_scene(half, "train")[0].rho) == (0.063, 0.30)


def test_plan_scene_unresolved_orbit():
    t = make_teacher(n_frames=3)
    t.c2w, t.orbit = None, OrbitSpec(radius=2.0, n_frames=3)
    with pytest.raises(ValueError, match="resolve_trajectory"):
        plan_scene(t, "train")


def test_plan_scene_short_trajectories():
    assert [p.frame for p in plan_scene(make_teacher(n_frames=3), "val")] == [0, 1, 2]
    assert [p.frame for p in plan_scene(make_teacher(n_frames=1), "test")] == [0]
