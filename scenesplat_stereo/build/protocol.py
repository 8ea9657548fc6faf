"""The SceneSplat-Stereo protocol (SPEC section 4; paper section 3 and appendix B) as pure functions.

No I/O: the teacher filter, the quality tiers, the scene splits, the reference-pose sampling for
validation and test scenes, and the per-sample camera plan (left, right, targets). Poses are OpenCV c2w
in metres (world units); B and rho are in the same units and can be overridden for other scales.
"""

from __future__ import annotations

import math
import random
import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np

from scenesplat_stereo.scene.cameras import fibonacci_directions, scale_intrinsics, stereo_rig
from scenesplat_stereo.scene.teachers import Rejection, Teacher
from scenesplat_stereo.shards.sample import sample_key

Split = Literal["train", "val", "test"]

MIN_TEACHER_PSNR = 30.0  # dB, kept strictly above (paper section 3, appendix B "Quality tiers")
NUM_TARGETS = 10  # Fibonacci-sphere target directions per reference pose (paper appendix B)
VAL_TARGETS = (0, 1, 2, 3)  # the first four stored targets per validation pair (appendix B)
VAL_PAIRS_PER_SCENE = 5  # evenly spaced validation pairs per held-out scene (appendix B)
TEST_PAIRS_PER_SCENE = 100  # evenly spaced test pairs per scene, ReplicaGS style (appendix C)
VAL_SCENES = {"ScanNetGS": 30, "ScanNetPPGS-V2": 20}  # validation scenes per subset (appendix B)
SPLIT_SEED = 42  # random.Random(42).sample per subset (appendix B "Scene splits and counts")
MASK_ALPHA_THRESHOLD = 0.5  # valid mask = rendered alpha >= 0.5 (appendix B)


@dataclass(frozen=True)
class Tier:
    """A teacher-quality tier: PSNR interval [low, high) (the first is open at 30 dB), stereo baseline
    B and target radius rho in metres."""

    psnr_low: float
    psnr_high: float
    baseline: float
    rho: float


# Paper Table 7 (appendix B "Quality tiers"): (30,35) dB -> B 0.05, rho 0.10; [35,40) -> 0.10, 0.20;
# [40,inf) -> 0.10, 0.30.
TIERS = (
    Tier(30.0, 35.0, 0.05, 0.10),
    Tier(35.0, 40.0, 0.10, 0.20),
    Tier(40.0, math.inf, 0.10, 0.30),
)


def keep_teacher(psnr: float | None, min_psnr: float | None = MIN_TEACHER_PSNR) -> bool:
    """The PSNR filter: keep a teacher strictly above ``min_psnr`` dB; ``min_psnr=None`` keeps every
    teacher, including those without a PSNR (which no threshold keeps)."""
    if min_psnr is None:
        return True
    return psnr is not None and psnr > min_psnr


def tier_for_psnr(psnr: float) -> Tier:
    """The tier of a teacher PSNR (dB) strictly above 30; ValueError for None, NaN or <= 30 dB."""
    if psnr is None or not psnr > TIERS[0].psnr_low:
        raise ValueError(f"no quality tier for teacher PSNR {psnr} dB (tiers start strictly above "
                         f"{TIERS[0].psnr_low} dB)")
    return next((t for t in TIERS if psnr < t.psnr_high), TIERS[-1])  # the last tier is open (+inf)


def filter_teachers(teachers: list[Teacher], min_psnr: float | None = MIN_TEACHER_PSNR
                    ) -> tuple[list[Teacher], list[Rejection]]:
    """(kept, dropped) by ``keep_teacher``; each drop's reason names the PSNR and the threshold."""
    kept, dropped = [], []
    for t in teachers:
        if keep_teacher(t.psnr, min_psnr):
            kept.append(t)
        else:
            why = "no PSNR (use --min-psnr none)" if t.psnr is None else f"PSNR {t.psnr:.2f} dB"
            dropped.append(Rejection(t.scene_id, t.ply_path, f"{why} not above {min_psnr} dB", t.subset))
    return kept, dropped


def split_scenes(scene_ids_by_subset: dict[str, list[str]], val_counts: dict[str, int] | None = None,
                 seed: int = SPLIT_SEED) -> dict[str, str]:
    """Scene splits: per subset, ``random.Random(seed).sample(sorted(ids), k)`` are "val", the rest
    "train"; k = ``val_counts`` of the subset (default ``VAL_SCENES``; 0 for subsets it does not name).
    Raises ValueError when a subset has fewer scenes than asked for or a scene id repeats."""
    counts = VAL_SCENES if val_counts is None else val_counts
    out: dict[str, str] = {}
    for subset, ids in sorted(scene_ids_by_subset.items()):
        ids = sorted(ids)
        k = counts.get(subset, 0)
        if not 0 <= k <= len(ids):
            raise ValueError(f"subset {subset!r} has {len(ids)} scenes; cannot hold out {k} for validation")
        val = set(random.Random(seed).sample(ids, k))
        for i in ids:
            if i in out:
                raise ValueError(f"scene id {i!r} appears more than once")
            out[i] = "val" if i in val else "train"
    return out


def _evenly_spaced(n_frames: int, k: int) -> list[int]:
    if n_frames <= k:
        return list(range(n_frames))
    return [int(i) for i in np.linspace(0, n_frames - 1, k).round()]


def validation_frames(n_frames: int, k: int = VAL_PAIRS_PER_SCENE) -> list[int]:
    """Frame indices of a validation scene: ``numpy.linspace(0, n-1, k).round()``; every frame once
    when there are no more than k."""
    return _evenly_spaced(n_frames, k)


def test_frames(n_frames: int, k: int = TEST_PAIRS_PER_SCENE) -> list[int]:
    """Frame indices of a test scene: ``numpy.linspace(0, n-1, k).round()``; every frame once when
    there are no more than k."""
    return _evenly_spaced(n_frames, k)


test_frames.__test__ = False  # a protocol function, not a pytest test


@dataclass(frozen=True)
class SamplePlan:
    """One sample (one reference pose): cameras as OpenCV c2w in world units, K in pixels at width x
    height, target_ids index the fixed Fibonacci directions (``c2w_targets[i]`` is direction
    ``target_ids[i]``), baseline and rho in world units, teacher_psnr in dB (None if unknown)."""

    scene: str
    subset: str
    frame: int
    key: str
    c2w_left: np.ndarray
    c2w_right: np.ndarray
    c2w_targets: np.ndarray
    target_ids: tuple[int, ...]
    K: np.ndarray
    width: int
    height: int
    baseline: float
    rho: float
    teacher_psnr: float | None
    split: Split = "train"


def plan_scene(teacher: Teacher, split: Split, baseline: float | None = None, rho: float | None = None,
               num_targets: int = NUM_TARGETS, resolution: tuple[int, int] | None = None) -> list[SamplePlan]:
    """The samples of one teacher for ``split``.

    Frames: "train" every frame in order; "val" ``validation_frames`` with targets ``VAL_TARGETS``;
    "test" ``test_frames`` with all targets. ``num_targets`` (1..10) keeps the first targets of the
    ten (val: of the first four). B and rho: as given (the build's ``--baseline``/``--rho``), else the
    teacher's own (``scene.json`` ``baseline``/``rho``), else the teacher's tier; a teacher with no
    tier (no PSNR, or kept below 30 dB by a lower ``--min-psnr``) gets the first tier's values and a
    warning. ``resolution`` (W, H) overrides the native size; K is rescaled with ``scale_intrinsics``.
    """
    if split not in ("train", "val", "test"):
        raise ValueError(f"split must be 'train', 'val' or 'test', got {split!r}")
    if not 1 <= num_targets <= NUM_TARGETS:
        raise ValueError(f"num_targets must be in 1..{NUM_TARGETS}, got {num_targets}")
    if teacher.c2w is None:
        raise ValueError(f"{teacher.scene_id}: orbit trajectory not resolved; call "
                         "teachers.resolve_trajectory(teacher, means) after loading the .ply")
    baseline = teacher.baseline if baseline is None else baseline
    rho = teacher.rho if rho is None else rho
    if baseline is None or rho is None:
        try:
            tier = tier_for_psnr(teacher.psnr)
        except ValueError:
            tier = TIERS[0]
            warnings.warn(f"{teacher.scene_id}: teacher PSNR {teacher.psnr} has no quality tier; using "
                          f"B = {tier.baseline} m, rho = {tier.rho} m (override with --baseline/--rho)",
                          stacklevel=2)
        baseline = tier.baseline if baseline is None else baseline
        rho = tier.rho if rho is None else rho
    n = teacher.num_frames
    if split == "train":
        frames, target_ids = list(range(n)), tuple(range(num_targets))
    elif split == "val":
        frames, target_ids = validation_frames(n), VAL_TARGETS[:num_targets]
    else:
        frames, target_ids = test_frames(n), tuple(range(num_targets))
    width, height = teacher.width, teacher.height
    Ks = teacher.Ks
    if resolution is not None and tuple(resolution) != (width, height):
        Ks = scale_intrinsics(Ks, (width, height), tuple(resolution))
        width, height = int(resolution[0]), int(resolution[1])
    directions = fibonacci_directions(NUM_TARGETS)[list(target_ids)]
    idx = np.asarray(frames, dtype=np.int64)
    right, targets = stereo_rig(teacher.c2w[idx], baseline, rho, directions)
    return [
        SamplePlan(scene=teacher.scene_id, subset=teacher.subset, frame=f, key=sample_key(teacher.scene_id, f),
                   c2w_left=teacher.c2w[f].copy(), c2w_right=right[i], c2w_targets=targets[i],
                   target_ids=target_ids, K=np.array(Ks[f], dtype=np.float64), width=width, height=height,
                   baseline=float(baseline), rho=float(rho), teacher_psnr=teacher.psnr, split=split)
        for i, f in enumerate(frames)
    ]
