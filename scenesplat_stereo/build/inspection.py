"""``scenesplat-stereo inspect OUT``: the per-subset table of paper Table 6, a contact sheet, and integrity
checks of a built dataset (SPEC sections 4 and 5).

Checks, for every shard listed in ``OUT/<split>/index.json``: the tar exists with the listed size and
sha256 and holds the listed keys in order; every sample has ``json``, ``left.jpg``, ``right.jpg`` and a
``target_<jj>.jpg`` and ``mask_<jj>.png`` per stored target (``left_depth.exr`` in all samples of a split
or none); the JSON has the SPEC fields and its poses follow the protocol (rigid c2w, right =
T_L Trans(B, 0, 0), target = T_L Trans(rho u_j) with the Fibonacci directions, all with the reference
orientation; a sample whose JSON lists ``target_frames``, as IRS samples do, has real frames as targets:
rigid and within rho of the left camera); images decode at width x height (RGB JPEGs, single-channel 0/255 PNG masks); and
``OUT/stats.json`` agrees with the counts read from the shards. ``--quick`` decodes the images of the
first sample of each shard only. Baselines and radii that differ from the teacher's PSNR tier are noted,
not failed (``--baseline``/``--rho`` and a teacher's ``scene.json`` ``baseline``/``rho`` override them on purpose).

The contact sheet (``--contact-sheet FILE``, default ``OUT/contact_sheet.png``) replaces only a sheet that inspect
wrote, unchanged (``common.ownership.check_replaceable_file``, checked before the dataset is read), and is written
atomically with its own manifest beside it (``.written-by.<name>``).
"""

from __future__ import annotations

import hashlib
import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from scenesplat_stereo.build.protocol import NUM_TARGETS, tier_for_psnr
from scenesplat_stereo.common.ownership import check_replaceable_file, write_owned_file
from scenesplat_stereo.common.text import whole_number
from scenesplat_stereo.scene.cameras import fibonacci_directions, right_camera, rigid_error, translation
from scenesplat_stereo.shards import webdataset as shards
from scenesplat_stereo.shards.encode import decode_image, encode_png
from scenesplat_stereo.shards.sample import SampleMeta, SampleMetaError, sample_key

POSE_TOLERANCE = 1e-6  # world units / unitless, for poses stored as float64 JSON
THUMB_WIDTH = 128  # pixels, contact-sheet thumbnails
OWNER = "scenesplat-stereo inspect"  # recorded beside the contact sheet: a later inspect may replace it


@dataclass
class InspectReport:
    """Counts per (subset, split): scenes, pairs, targets and the teacher PSNRs; ``problems`` fail the
    inspection, ``notes`` do not."""

    counts: dict[tuple[str, str], dict] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    samples: int = 0
    contact_sheet: Path | None = None

    @property
    def ok(self) -> bool:
        return not self.problems


def check_sample(key: str, members: dict[str, bytes], decode: bool) -> tuple[SampleMeta | None, list[str], list[str]]:
    """(record, problems, notes) of one sample; ``decode`` also decodes and checks every image."""
    problems, notes = [], []
    if "json" not in members:
        return None, [f"{key}: json member missing"], notes
    try:
        meta = SampleMeta.from_json(members["json"], f"{key}.json")
    except SampleMetaError as e:
        return None, [str(e)], notes
    ids = list(meta.target_ids)
    expected = {"json", "left.jpg", "right.jpg"} | {f"target_{j:02d}.jpg" for j in ids} | {f"mask_{j:02d}.png" for j in ids}
    have = set(members) - {"left_depth.exr"}
    if expected - have:
        problems.append(f"{key}: missing members {sorted(expected - have)}")
    if have - expected:
        problems.append(f"{key}: unexpected members {sorted(have - expected)}")
    if key != meta.key or key != sample_key(meta.scene, meta.frame):
        problems.append(f"{key}.json: scene/frame do not match the key")
    problems += _check_poses(key, meta)
    if meta.teacher_psnr is not None and meta.teacher_psnr > 30.0:
        tier = tier_for_psnr(meta.teacher_psnr)
        if (meta.baseline, meta.rho) != (tier.baseline, tier.rho):
            notes.append(f"{meta.scene}: B={meta.baseline}, rho={meta.rho} differ from the tier of "
                         f"{meta.teacher_psnr} dB (B={tier.baseline}, rho={tier.rho})")
    if decode:
        problems += _check_images(key, members, meta)
    return meta, problems, notes


def _check_poses(key: str, meta: SampleMeta) -> list[str]:
    K, left, targets, ids = meta.K, meta.c2w_left, meta.targets, list(meta.target_ids)
    problems = []
    if not np.allclose(K[2], (0, 0, 1)):
        problems.append(f"{key}.json: K is not a pinhole matrix with positive focal lengths")
    if rigid_error(left) > POSE_TOLERANCE:
        return problems + [f"{key}.json: c2w_left is not a rigid 4x4 transform"]
    if not all(0 <= j < NUM_TARGETS for j in ids):
        return problems + [f"{key}.json: {len(targets)} targets for target_ids {ids}"]
    B, rho = meta.baseline, meta.rho
    scale = max(1.0, float(np.abs(left[:3, 3]).max()))
    if meta.c2w_right is not None:
        if np.abs(meta.c2w_right - right_camera(left, B)).max() > POSE_TOLERANCE * scale:
            problems.append(f"{key}.json: c2w_right is not c2w_left Trans(B={B}, 0, 0)")
    if meta.target_frames is not None:  # real frames as targets (IRS, SPEC section 6): rigid, within rho
        frames = meta.target_frames
        if len(frames) != len(targets):
            return problems + [f"{key}.json: target_frames does not list one frame per target"]
        dist = np.linalg.norm(targets[:, :3, 3] - left[:3, 3], axis=1)
        bad = [ids[i] for i, t in enumerate(targets)
               if rigid_error(t) > POSE_TOLERANCE or dist[i] > rho + POSE_TOLERANCE * scale]
        if bad:
            problems.append(f"{key}.json: targets {bad} are not rigid or lie farther than rho={rho} from c2w_left")
        return problems
    want = left[None] @ translation(rho * fibonacci_directions(NUM_TARGETS)[ids])
    bad = np.abs(targets - want).max(axis=(1, 2)) > POSE_TOLERANCE * scale
    if bad.any():
        problems.append(f"{key}.json: targets {[ids[i] for i in np.flatnonzero(bad)]} are not c2w_left Trans(rho u_j)")
    return problems


def _check_images(key: str, members: dict[str, bytes], meta: SampleMeta) -> list[str]:
    problems, size, ids = [], (meta.height, meta.width), meta.target_ids
    for name in ["left.jpg", "right.jpg"] + [f"target_{j:02d}.jpg" for j in ids] + [f"mask_{j:02d}.png" for j in ids] \
            + (["left_depth.exr"] if "left_depth.exr" in members else []):
        if name not in members:
            continue
        try:
            img = decode_image(members[name], name.rsplit(".", 1)[1])
        except ValueError as e:
            problems.append(f"{key}.{name}: does not decode ({e})")
            continue
        channels = 3 if name.endswith(".jpg") else 1
        if img.shape != size + (channels,):
            problems.append(f"{key}.{name}: shape {img.shape}, expected {size + (channels,)}")
        elif name.endswith(".png") and not np.isin(img, (0, 255)).all():
            problems.append(f"{key}.{name}: mask values other than 0 and 255")
        elif name.endswith(".exr") and (np.isnan(img).any() or (img < 0).any()):
            problems.append(f"{key}.{name}: NaN or negative depth")
    return problems


def inspect_dataset(out: Path, contact_sheet: Path | None = None, sheet_samples: int = 4, quick: bool = False,
                    progress: bool = True) -> InspectReport:
    """Check a built dataset (see the module docstring); write the contact sheet PNG when asked (ValueError
    naming --contact-sheet, before anything is read, when it may not be replaced)."""
    if contact_sheet is not None:
        contact_sheet = check_replaceable_file(contact_sheet, "--contact-sheet", OWNER)
    out, report = Path(out), InspectReport()
    scenes: dict[tuple[str, str, str], dict] = {}
    sheet: list[tuple[str, dict[str, bytes]]] = []
    sheet_scenes: set[str] = set()
    splits = sorted(p.parent.name for p in out.glob(f"*/{shards.INDEX_NAME}"))
    if not splits:
        report.problems.append(f"{out}: no <split>/{shards.INDEX_NAME}; not a built dataset")
    for split in splits:
        try:
            index = json.loads((out / split / shards.INDEX_NAME).read_text())
            entries = [e for e in index["shards"] if all(k in e for k in ("name", "bytes", "sha256", "keys"))]
            if len(entries) != len(index["shards"]):
                raise KeyError("shards[].name/bytes/sha256/keys")
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as e:
            report.problems.append(f"{out / split / shards.INDEX_NAME}: unreadable ({type(e).__name__}: {e})")
            continue
        depth_in: set[bool] = set()
        for entry in tqdm(entries, desc=f"inspect {split}", unit="shard", disable=not progress):
            path = out / split / entry["name"]
            if not path.is_file():
                report.problems.append(f"{path}: listed in index.json but missing")
                continue
            data = path.read_bytes()
            if len(data) != entry["bytes"] or hashlib.sha256(data).hexdigest() != entry["sha256"]:
                report.problems.append(f"{path}: size or sha256 differs from index.json")
            keys = []
            try:
                for i, (key, members) in enumerate(shards.iter_shard(path)):
                    keys.append(key)
                    meta, problems, notes = check_sample(key, members, decode=not quick or i == 0)
                    report.problems += problems
                    report.notes += notes
                    report.samples += 1
                    depth_in.add("left_depth.exr" in members)
                    if meta is None:
                        continue
                    acc = scenes.setdefault((meta.subset, split, meta.scene),
                                            {"psnr": meta.teacher_psnr, "pairs": 0, "targets": 0})
                    acc["pairs"] += 1
                    acc["targets"] += meta.num_targets
                    if len(sheet) < sheet_samples and meta.scene not in sheet_scenes:
                        sheet.append((f"{split}/{key}", members))
                        sheet_scenes.add(meta.scene)
            except Exception as e:  # noqa: BLE001  (any unreadable tar is a failed check, named)
                report.problems.append(f"{path}: unreadable tar ({type(e).__name__}: {e})")
            if keys != entry["keys"]:
                report.problems.append(f"{path}: keys differ from index.json")
        if len(depth_in) > 1:
            report.problems.append(f"{out / split}: left_depth.exr in some samples but not all")
    _table_counts(report, scenes)
    _check_stats(out, report, scenes)
    report.notes = sorted(set(report.notes))
    if contact_sheet is not None and sheet:
        report.contact_sheet = write_owned_file(contact_sheet, encode_png(_contact_sheet(sheet)), OWNER)
    return report


def _table_counts(report: InspectReport, scenes: dict) -> None:
    for (subset, split, _), acc in sorted(scenes.items()):
        row = report.counts.setdefault((subset, split), {"scenes": 0, "pairs": 0, "targets": 0, "psnr": []})
        row["scenes"] += 1
        row["pairs"] += acc["pairs"]
        row["targets"] += acc["targets"]
        row["psnr"].append(acc["psnr"])


def _check_stats(out: Path, report: InspectReport, scenes: dict) -> None:
    path = out / shards.STATS_NAME
    if not path.is_file():
        report.problems.append(f"{path}: missing")
        return
    try:
        stats = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        report.problems.append(f"{path}: unreadable ({e})")
        return
    for (subset, split), row in report.counts.items():
        got = stats.get("subsets", {}).get(subset, {}).get("splits", {}).get(split, {})
        want = {k: row[k] for k in ("scenes", "pairs", "targets")}
        if {k: got.get(k) for k in want} != want:
            report.problems.append(f"{path}: {subset}/{split} counts {got} differ from the shards {want}")


def table(report: InspectReport) -> str:
    """Markdown table in the layout of paper Table 6: per subset and split, scenes, stereo pairs, target
    views and the mean teacher PSNR (dB, over the subset's scenes of all splits), then totals per split."""
    lines = ["| Subset | Split | Scenes | Stereo pairs | Target views | Teacher PSNR |", "|---|---|---:|---:|---:|---:|"]
    by_subset: dict[str, list] = defaultdict(list)
    for (subset, _), row in report.counts.items():
        by_subset[subset] += row["psnr"]
    totals: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0])
    for (subset, split), row in report.counts.items():
        psnrs = [p for p in by_subset[subset] if p is not None]
        mean = f"{np.mean(psnrs):.2f}" if psnrs else "--"
        lines.append(f"| {subset} | {split} | {row['scenes']} | {row['pairs']} | {row['targets']} | {mean} |")
        for i, k in enumerate(("scenes", "pairs", "targets")):
            totals[split][i] += row[k]
    for split, (s, p, t) in sorted(totals.items()):
        lines.append(f"| **Total** | {split} | {s} | {p} | {t} | -- |")
    return "\n".join(lines)


def _contact_sheet(samples: list[tuple[str, dict[str, bytes]]]) -> np.ndarray:
    """Rows of [label | left | right | targets] over [ | | | masks] thumbnails, uint8 [H, W, 3]."""
    rows = []
    for label, members in samples:
        meta = SampleMeta.from_json(members["json"], f"{label}.json")
        ids = meta.target_ids
        th = max(1, round(THUMB_WIDTH * meta.height / meta.width))

        def thumb(name: str) -> np.ndarray:
            if name not in members:
                return np.zeros((th, THUMB_WIDTH, 3), np.uint8)
            img = decode_image(members[name], name.rsplit(".", 1)[1])
            img = np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img
            return cv2.resize(img, (THUMB_WIDTH, th), interpolation=cv2.INTER_AREA)

        blank = np.full((th, THUMB_WIDTH, 3), 40, np.uint8)
        top = [thumb("left.jpg"), thumb("right.jpg")] + [thumb(f"target_{j:02d}.jpg") for j in ids]
        bottom = [blank, blank] + [thumb(f"mask_{j:02d}.png") for j in ids]
        band = np.concatenate([np.concatenate(top, 1), np.concatenate(bottom, 1)], 0)
        head = np.full((18, band.shape[1], 3), 255, np.uint8)
        names = ["left", "right"] + [f"target {j}" for j in ids]
        text = f"{label}  ({meta.width}x{meta.height}, B={meta.baseline}, rho={meta.rho})"
        cv2.putText(head, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        for i, name in enumerate(names):
            cv2.putText(band, name, (i * THUMB_WIDTH + 3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 0), 1, cv2.LINE_AA)
        rows.append(np.concatenate([head, band], 0))
    width = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0))) for r in rows], 0)


def add_arguments(p) -> None:
    p.add_argument("out", type=Path, help="a folder written by `scenesplat-stereo build`")
    p.add_argument("--contact-sheet", type=Path, default=None,
                   help="PNG to write: left, right, targets and masks of a few samples (default OUT/contact_sheet.png)")
    p.add_argument("--sheet-samples", type=whole_number("--sheet-samples", 0), default=4, help="samples on the contact sheet, one per scene (default 4)")
    p.add_argument("--quick", action="store_true", help="decode only the first sample of each shard")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    """CLI entry: print the table, notes and problems; exit 1 when any check fails, 2 when OUT is no folder."""
    if not Path(args.out).is_dir():
        raise ValueError(f"OUT {args.out}: not a folder")
    sheet = args.contact_sheet or Path(args.out) / "contact_sheet.png"
    report = inspect_dataset(args.out, sheet, args.sheet_samples, args.quick, progress=not args.no_progress)
    print(table(report))
    print(f"\n{report.samples} samples checked" + (f"; contact sheet: {report.contact_sheet}" if report.contact_sheet else ""))
    for note in report.notes[:20]:
        print(f"note: {note}")
    for problem in report.problems[:50]:
        print(f"FAIL: {problem}")
    if len(report.problems) > 50:
        print(f"... and {len(report.problems) - 50} more problems")
    print("OK" if report.ok else f"{len(report.problems)} problems")
    return 0 if report.ok else 1
