"""IRS target selection and shards (paper appendix F, "IRS target selection and training"; SPEC section 6).

    irs-targets POSES_DIR --out SHARDS_DIR [--val-variants 8] [--min-targets 4]

(the installed command; ``python pipelines/irs_targets.py`` and ``python -m pipelines.irs_targets`` run the
same). POSES_DIR is the output of ``irs-pose-recovery``: only variants whose report.json says ``kept`` are
used. Targets are existing left frames of the same variant:
- reference frames: the first registered frame, then each frame that moved >= 5 cm or turned >= 5 deg
  from the last reference (in frame order);
- candidates for a reference: other registered frames 3-40 cm away (camera centres), turned <= 30 deg, with
  frustum coverage >= 0.4: the fraction of the reference's depth points (z = 48 / d from its disparity, on
  a pixel grid) that project in front of the candidate (z > 0) and inside its image, without an occlusion
  test;
- up to 8 targets per reference, coverage closest to 0.8 first (ties: lower frame number).

Splits (appendix F: 55 training and 8 validation variants): ``protocol.split_scenes`` with
``--val-variants`` for the subset "IRS". Training samples are the references with at least
``--min-targets`` targets (4, as the paper's training pairs), with all their targets; validation samples
are 5 evenly spaced references among those with at least 4 targets, with their first 4 targets.

Shards follow SPEC section 5 (``OUT/<split>/shard-*.tar``, ``index.json``, ``OUT/stats.json``): left and
right JPEGs (quality 92) re-encoded from the IRS PNGs, ``target_<jj>.jpg`` = the selected left frames in
selection order, ``mask_<jj>.png`` all valid (255: real images have no holes), and the JSON with
``targets`` = the target c2w (OpenCV, metres), ``target_ids`` = 0..T-1, ``teacher_psnr`` null, ``rho`` =
the largest reference-to-target distance (metres; IRS targets are not on a sphere), plus
``target_frames`` (IRS frame numbers) and ``target_coverage``.

Exit status (``scenesplat_stereo.common.commandline``): 0 done, 2 bad arguments or input (one line naming the flag or
file, nothing removed), 130 interrupted, 1 internal error.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from pipelines.irs import IRS_FOCAL_BASELINE, depth_from_disparity, read_disparity
from scenesplat_stereo.common.commandline import Parser, run_command
from scenesplat_stereo.common.text import format_table, key_safe_name, positive_number, whole_number
from scenesplat_stereo.scene.cameras import rotation_angle_deg

# Paper appendix F, "IRS target selection and training".
REFERENCE_MIN_TRANSLATION = 0.05  # metres since the last reference frame ...
REFERENCE_MIN_ROTATION_DEG = 5.0  # ... or degrees
TARGET_MIN_DISTANCE = 0.03  # metres, reference to target camera centre
TARGET_MAX_DISTANCE = 0.40  # metres
TARGET_MAX_ROTATION_DEG = 30.0
TARGET_MIN_COVERAGE = 0.4  # projected-point frustum coverage
TARGET_COVERAGE_GOAL = 0.8  # targets ranked by |coverage - 0.8|
MAX_TARGETS = 8
TRAIN_MIN_TARGETS = 4  # training pairs have at least four targets
VAL_VARIANTS = 8  # validation scene variants (55 training + 8 validation)
OWNER = "irs-targets"  # recorded in OUT's manifest: a later run may replace what it wrote there
IRS_SUBSET = "IRS"
# Not from the paper: the reference depth map is sampled every DEPTH_STRIDE pixels (pixel centres) to
# estimate the coverage fraction (1 = every pixel).
DEPTH_STRIDE = 4


@dataclass(frozen=True)
class TargetRules:
    """The selection rules (defaults: paper appendix F). All bounds are inclusive."""

    reference_min_translation: float = REFERENCE_MIN_TRANSLATION
    reference_min_rotation_deg: float = REFERENCE_MIN_ROTATION_DEG
    min_distance: float = TARGET_MIN_DISTANCE
    max_distance: float = TARGET_MAX_DISTANCE
    max_rotation_deg: float = TARGET_MAX_ROTATION_DEG
    min_coverage: float = TARGET_MIN_COVERAGE
    coverage_goal: float = TARGET_COVERAGE_GOAL
    max_targets: int = MAX_TARGETS
    depth_stride: int = DEPTH_STRIDE


def select_references(c2w: np.ndarray, rules: TargetRules = TargetRules()) -> list[int]:
    """Indices (into ``c2w`` [F,4,4], frame order) of the reference frames: the first, then each frame
    >= ``reference_min_translation`` metres or >= ``reference_min_rotation_deg`` from the last reference."""
    if len(c2w) == 0:
        return []
    refs = [0]
    for i in range(1, len(c2w)):
        last = c2w[refs[-1]]
        moved = np.linalg.norm(c2w[i, :3, 3] - last[:3, 3])
        turned = rotation_angle_deg(last, c2w[i])
        if moved >= rules.reference_min_translation or turned >= rules.reference_min_rotation_deg:
            refs.append(i)
    return refs


def depth_points(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, stride: int = 1) -> np.ndarray:
    """World points [M,3] of the depth map [H,W] (metres, NaN or <= 0 = no depth) at the pixel centres
    (u + 0.5, v + 0.5) of every ``stride``-th pixel, through K and c2w (OpenCV)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[v, u]
    ok = np.isfinite(z) & (z > 0)
    u, v, z = u[ok] + 0.5, v[ok] + 0.5, z[ok]
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def frustum_coverage(points: np.ndarray, c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> float:
    """Fraction of world ``points`` [M,3] in front of the camera (z > 0) whose projection falls inside its
    image, [0, width) x [0, height) (no occlusion test). 0 when there are no points."""
    if len(points) == 0:
        return 0.0
    R, t = c2w[:3, :3], c2w[:3, 3]
    cam = (points - t) @ R
    front = cam[:, 2] > 0
    z = np.where(front, cam[:, 2], 1.0)
    u = K[0, 0] * cam[:, 0] / z + K[0, 2]
    v = K[1, 1] * cam[:, 1] / z + K[1, 2]
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return float(inside.mean())


@dataclass(frozen=True)
class Target:
    """A selected target: index into the variant's registered frames, distance (m), rotation (deg),
    coverage."""

    index: int
    distance: float
    rotation_deg: float
    coverage: float


def select_targets(ref: int, c2w: np.ndarray, points: np.ndarray, K: np.ndarray, width: int, height: int,
                   rules: TargetRules = TargetRules()) -> list[Target]:
    """Targets of reference ``ref`` among the frames ``c2w`` [F,4,4], given the reference's world depth
    ``points``: candidates within the distance and rotation bounds with coverage >= ``min_coverage``,
    ranked by |coverage - coverage_goal| (ties: lower index), at most ``max_targets``."""
    dist = np.linalg.norm(c2w[:, :3, 3] - c2w[ref, :3, 3], axis=1)
    rot = rotation_angle_deg(c2w[ref], c2w)
    near = (dist >= rules.min_distance) & (dist <= rules.max_distance) & (rot <= rules.max_rotation_deg)
    near[ref] = False
    found = []
    for j in np.flatnonzero(near):
        cov = frustum_coverage(points, c2w[j], K, width, height)
        if cov >= rules.min_coverage:
            found.append(Target(int(j), float(dist[j]), float(rot[j]), cov))
    found.sort(key=lambda t: (abs(t.coverage - rules.coverage_goal), t.index))
    return found[: rules.max_targets]


@dataclass
class Reference:
    """One reference pair of a variant with its targets (indices into the variant's poses.json frames)."""

    index: int
    targets: list[Target]


def select_variant(poses: dict, source: Path, rules: TargetRules = TargetRules(),
                   focal_baseline: float = IRS_FOCAL_BASELINE) -> list[Reference]:
    """References and their targets for one variant's ``poses.json`` (``source``: its image folder)."""
    frames = poses["frames"]
    c2w = np.array([f["c2w_left"] for f in frames], dtype=np.float64).reshape(-1, 4, 4)
    K = np.array(poses["K"], dtype=np.float64)
    out = []
    for r in select_references(c2w, rules):
        depth = depth_from_disparity(read_disparity(Path(source) / frames[r]["disparity"]), focal_baseline)
        points = depth_points(depth, K, c2w[r], rules.depth_stride)
        out.append(Reference(r, select_targets(r, c2w, points, K, poses["width"], poses["height"], rules)))
    return out


def split_samples(refs: Sequence[Reference], split: str, min_targets: int = TRAIN_MIN_TARGETS
                  ) -> list[Reference]:
    """The references a split stores: "train" every reference with >= ``min_targets`` targets (all its
    targets); "val" ``protocol.validation_frames`` (5 evenly spaced) among those with at least
    ``len(VAL_TARGETS)`` targets, each cut to its first ``len(VAL_TARGETS)`` targets."""
    from scenesplat_stereo.build.protocol import VAL_TARGETS, validation_frames

    if split == "train":
        return [r for r in refs if len(r.targets) >= max(1, min_targets)]
    if split != "val":
        raise ValueError(f"split must be 'train' or 'val', got {split!r}")
    k = len(VAL_TARGETS)
    pool = [r for r in refs if len(r.targets) >= k]
    return [Reference(pool[i].index, pool[i].targets[:k]) for i in validation_frames(len(pool))]


def read_rgb(path: Path) -> np.ndarray:
    """An 8-bit image file as uint8 [H, W, 3] (grey repeated, alpha dropped); ValueError naming the file."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    pixels = buf.get_pixels(oiio.UINT8)
    if buf.has_error or pixels is None or pixels.ndim != 3:
        raise ValueError(f"{path}: cannot read image ({buf.geterror() or 'no pixels'})")
    if pixels.shape[2] < 3:
        pixels = np.repeat(pixels[..., :1], 3, axis=2)
    return np.ascontiguousarray(pixels[..., :3])


@dataclass
class VariantSelection:
    """A kept variant, its split, poses and selected references (all of them, before the split's cut)."""

    name: str
    split: str
    poses: dict
    source: Path
    references: list[Reference]


_POSES_FIELDS = ("source", "frames", "K", "width", "height", "baseline")
_FRAME_FIELDS = ("frame", "left", "right", "disparity", "c2w_left", "c2w_right")


def read_poses(path: Path) -> dict:
    """A variant's poses.json, checked: ValueError naming the file and the missing or malformed field."""
    try:
        poses = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{path}: unreadable JSON ({e})") from None
    if not isinstance(poses, dict):
        raise ValueError(f"{path}: expected a JSON object")
    missing = [k for k in _POSES_FIELDS if k not in poses]
    if missing:
        raise ValueError(f"{path}: missing field(s) {', '.join(missing)}")
    if not isinstance(poses["frames"], list) or not poses["frames"]:
        raise ValueError(f"{path}: frames: expected a non-empty list")
    for i, f in enumerate(poses["frames"]):
        gone = [k for k in _FRAME_FIELDS if not isinstance(f, dict) or k not in f]
        if gone:
            raise ValueError(f"{path}: frames[{i}]: missing field(s) {', '.join(gone)}")
        for k in ("c2w_left", "c2w_right"):
            if np.asarray(f[k], dtype=object).shape != (4, 4):
                raise ValueError(f"{path}: frames[{i}].{k}: expected a 4x4 matrix")
    if np.asarray(poses["K"], dtype=object).shape != (3, 3):
        raise ValueError(f"{path}: K: expected a 3x3 matrix")
    for k in ("width", "height"):
        if isinstance(poses[k], bool) or not isinstance(poses[k], int) or poses[k] < 1:
            raise ValueError(f"{path}: {k}: expected a whole number of pixels >= 1, got {poses[k]!r}")
    return poses


def _select(args: tuple[str, str, Path, TargetRules, float]) -> VariantSelection:
    name, split, poses_path, rules, focal_baseline = args
    poses = read_poses(poses_path)
    source = Path(poses["source"])
    return VariantSelection(name, split, poses, source, select_variant(poses, source, rules, focal_baseline))


def kept_variants(poses_dir: Path) -> list[str]:
    """Variant folders of ``poses_dir`` whose report.json says kept and that have a poses.json, sorted."""
    names = []
    for d in sorted(p for p in Path(poses_dir).iterdir() if p.is_dir()):
        try:
            kept = json.loads((d / "report.json").read_text()).get("kept") is True
        except (OSError, ValueError):
            continue
        if kept and (d / "poses.json").is_file():
            names.append(d.name)
    return names


def sample_images(sel: VariantSelection, ref: Reference):
    """The ``encode.SampleImages`` of one stored reference pair (at least one target; images read from the
    IRS folder)."""
    from scenesplat_stereo.build.protocol import SamplePlan
    from scenesplat_stereo.shards.encode import SampleImages
    from scenesplat_stereo.shards.sample import SampleMeta, sample_key

    frames, w, h = sel.poses["frames"], sel.poses["width"], sel.poses["height"]
    f = frames[ref.index]
    key = sample_key(sel.name, f["frame"])
    targets = [frames[t.index] for t in ref.targets]
    plan = SamplePlan(scene=sel.name, subset=IRS_SUBSET, frame=f["frame"], key=key,
                      c2w_left=np.array(f["c2w_left"]), c2w_right=np.array(f["c2w_right"]),
                      c2w_targets=np.array([t["c2w_left"] for t in targets]).reshape(-1, 4, 4),
                      target_ids=tuple(range(len(targets))), K=np.array(sel.poses["K"]), width=w, height=h,
                      baseline=float(sel.poses["baseline"]), rho=max((t.distance for t in ref.targets), default=0.0),
                      teacher_psnr=None, split=sel.split)
    meta = replace(SampleMeta.from_plan(plan), target_frames=tuple(t["frame"] for t in targets),
                   target_coverage=tuple(t.coverage for t in ref.targets))
    return SampleImages(key=key, left=read_rgb(sel.source / f["left"]), right=read_rgb(sel.source / f["right"]),
                        targets=np.stack([read_rgb(sel.source / t["left"]) for t in targets]),
                        masks=np.ones((len(targets), h, w), dtype=bool), target_ids=plan.target_ids,
                        meta=meta.to_json())


def write_irs_shards(poses_dir: Path, out: Path, val_variants: int = VAL_VARIANTS,
                     min_targets: int = TRAIN_MIN_TARGETS, rules: TargetRules = TargetRules(),
                     focal_baseline: float = IRS_FOCAL_BASELINE, samples_per_shard: int = 256, workers: int = 1,
                     progress: bool = True) -> list[dict]:
    """Select targets for every kept variant of ``poses_dir`` (``workers`` processes) and write the train
    and val shards, their index.json and OUT/stats.json (earlier shards of those splits are removed first).
    Returns one row per variant (split, references, stored pairs and targets, mean coverage) and writes
    them to ``OUT/irs_selection.json``."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    from scenesplat_stereo.build.protocol import split_scenes
    from scenesplat_stereo.common.commandline import quiet_worker_interrupts
    from scenesplat_stereo.common.files import atomic_write_json
    from scenesplat_stereo.common.ownership import OwnedFolder, check_apart, check_replaceable
    from scenesplat_stereo.shards.encode_pool import SampleEncoder
    from scenesplat_stereo.shards.webdataset import (ShardWriter, collect_stats, finished_shards, remove_shard,
                                                     write_index, write_stats)

    if samples_per_shard < 1:
        raise ValueError(f"--samples-per-shard {samples_per_shard}: must be >= 1")
    if rules.depth_stride < 1:
        raise ValueError(f"--depth-stride {rules.depth_stride}: must be >= 1")
    if not Path(poses_dir).is_dir():
        raise ValueError(f"POSES_DIR {poses_dir}: not a folder")
    names = kept_variants(poses_dir)
    if not names:
        raise ValueError(f"{poses_dir}: no kept variant (report.json 'kept': true with a poses.json)")
    for n in names:
        if key_safe_name(n) != n:
            raise ValueError(f"{Path(poses_dir) / n}: variant name {n!r} is not usable in sample keys ('.', "
                             f"whitespace or '__'); rename the folder (e.g. {key_safe_name(n)!r})")
    for n in names:
        read_poses(Path(poses_dir) / n / "poses.json")  # every input checked before anything is removed
    out = check_replaceable(out, "--out", OWNER)
    check_apart(out, "--out", {"POSES_DIR": poses_dir}, replaced=True)
    splits = split_scenes({IRS_SUBSET: names}, {IRS_SUBSET: val_variants})
    jobs = [(n, splits[n], Path(poses_dir) / n / "poses.json", rules, focal_baseline) for n in names]
    bar = dict(desc="select targets", unit="variant", disable=not progress)
    if workers > 1:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=quiet_worker_interrupts) as pool:
            selections = list(tqdm(pool.map(_select, jobs), total=len(jobs), **bar))
    else:
        selections = [_select(j) for j in tqdm(jobs, **bar)]
    with OwnedFolder(out, OWNER):  # every file it holds is recorded as this command's, however it ends
        rows = []
        for split in ("train", "val"):
            chosen = [(s, r) for s in selections if s.split == split
                      for r in split_samples(s.references, split, min_targets)]
            for number in finished_shards(out, split):
                remove_shard(out, split, number)
            with ShardWriter(out, split, samples_per_shard) as writer, \
                    SampleEncoder(writer.add, workers=max(1, workers)) as encoder:
                for sel, ref in tqdm(chosen, desc=f"{split} shards", unit="pair", disable=not progress):
                    encoder.submit(sample_images(sel, ref))
            write_index(out, split)
            for s in (s for s in selections if s.split == split):
                stored = [r for sel, r in chosen if sel is s]
                cov = [t.coverage for r in stored for t in r.targets]
                rows.append({"variant": s.name, "split": split, "registered": len(s.poses["frames"]),
                             "references": len(s.references), "pairs": len(stored),
                             "targets": sum(len(r.targets) for r in stored),
                             "mean_coverage": float(np.mean(cov)) if cov else None})
        write_stats(out, collect_stats(out))
        atomic_write_json(Path(out) / "irs_selection.json", {"rules": asdict(rules),
                                                             "min_targets": min_targets, "variants": rows})
    return rows


def summary_table(rows: list[dict]) -> str:
    """One line per variant (split, registered frames, references, stored pairs and targets, mean
    coverage) and a total per split."""
    table = [("variant", "split", "frames", "refs", "pairs", "targets", "coverage")]
    for r in rows:
        cov = "-" if r["mean_coverage"] is None else f"{r['mean_coverage']:.3f}"
        table.append((r["variant"], r["split"], str(r["registered"]), str(r["references"]), str(r["pairs"]),
                      str(r["targets"]), cov))
    for split in ("train", "val"):
        sub = [r for r in rows if r["split"] == split]
        table.append((f"total {len(sub)}", split, str(sum(r["registered"] for r in sub)),
                      str(sum(r["references"] for r in sub)), str(sum(r["pairs"] for r in sub)),
                      str(sum(r["targets"] for r in sub)), ""))
    return format_table(table, align="l" * len(table[0]), rule=True)


def main(argv: list[str] | None = None) -> int:
    """``irs-targets``; errors as every command's (``commandline.run_command``)."""
    p = Parser(prog="irs-targets", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("poses_dir", type=Path, metavar="POSES_DIR", help="output folder of irs-pose-recovery")
    p.add_argument("--out", type=Path, required=True, help="shard folder (OUT/<split>/shard-*.tar)")
    p.add_argument("--val-variants", type=whole_number("--val-variants", 0), default=VAL_VARIANTS,
                   help=f"validation variants, chosen with random.Random(42) (default {VAL_VARIANTS})")
    p.add_argument("--min-targets", type=whole_number("--min-targets"), default=TRAIN_MIN_TARGETS,
                   help=f"training pairs need at least this many targets (default {TRAIN_MIN_TARGETS})")
    p.add_argument("--depth-stride", type=whole_number("--depth-stride"), default=DEPTH_STRIDE,
                   help=f"coverage uses every n-th pixel of the reference depth (default {DEPTH_STRIDE})")
    p.add_argument("--focal-baseline", type=positive_number("--focal-baseline"), default=IRS_FOCAL_BASELINE,
                   help=f"fx * B in pixels * metres for z = fx B / d (default {IRS_FOCAL_BASELINE:g})")
    p.add_argument("--samples-per-shard", type=whole_number("--samples-per-shard"), default=256, help="samples per tar (default 256)")
    p.add_argument("--workers", type=whole_number("--workers"), default=1,
                   help="processes for target selection and threads for JPEG encoding (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)
    return run_command(p, argv)


def _run(args: argparse.Namespace) -> int:
    rows = write_irs_shards(args.poses_dir, args.out, args.val_variants, args.min_targets,
                            TargetRules(depth_stride=args.depth_stride), args.focal_baseline,
                            args.samples_per_shard, args.workers, not args.no_progress)
    print(summary_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
