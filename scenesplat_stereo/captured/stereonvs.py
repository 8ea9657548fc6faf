"""``scenesplat-stereo import stereonvs``: the StereoNVS-Real benchmark (StereoNeRF, Lee et al., CVPR 2024;
CC BY-NC 3.0) as SceneSplat-Stereo test shards (SPEC section 5) that ``sgmodel eval --split test`` reads.

Input, one folder per scene under ROOT, as StereoNeRF's own loader (``data/llff_stereo.py``) reads it:

    ROOT/<scene>/images/left/*      left images, in name order
    ROOT/<scene>/images/right/*     right images, the same names
    ROOT/<scene>/poses_bounds.npy   [2N, 17] LLFF cameras (scenesplat_stereo.captured.llff): rows 0..N-1 the left
                                    images, rows N..2N-1 the right ones; one focal for all

Cameras. K comes from poses_bounds' focal at its H x W, scaled per axis to the size of the image files
(principal point at the centre), so fx and fy stay apart when the aspect ratio changed. Poses are COLMAP's,
in arbitrary units: the rig's physical baseline B (``--baseline``, metres) fixes the scale. Each pair
gives s_i = B / |C_R,i - C_L,i| (metres per unit); the scene's scale is their median, and a scene whose
pairs differ from it by more than ``--scale-tolerance`` (relative) is refused, naming the pair. Camera
centres are multiplied by s; c2w are OpenCV (x right, y down, z forward), metres.

Rectification. The model takes a rectified pair: the right camera is the left one moved by B along its
own x axis, same orientation. COLMAP estimates the right cameras on their own, so each pair is checked:
the rotation between its two cameras and the angle between its baseline (in the left camera's axes) and
+x must both stay within ``--rectification-tolerance`` degrees, else the scene is refused naming the pair
(left and right swapped gives 180 degrees). The stored ``c2w_right`` is the ideal T_L Trans(B, 0, 0):
the images are rectified by the camera, the estimated right pose only serves the checks and the scale.

Protocol (paper section 5 and appendix C: "8 real-world scenes, 224 stereo-to-target evaluation pairs").
As in StereoNeRF, every left frame i is a target exactly once; its input is the stereo pair j != i whose
left camera centre is nearest to i's (ties: the lower j), so a target is never its own input. A sample is
one input pair j with all the frames that chose it as targets, in frame order (SPEC section 5: one sample
per reference pose; key ``<scene>__<j:06d>``; ``target_frames`` lists the frames); pairs nobody chose are
not stored. The paper's 224 pairs are therefore 224 targets (the number of left frames of its 8 scenes);
``stats.json`` counts them as ``targets`` and the distinct input pairs as ``pairs``. ``rho`` is the
farthest target's distance (metres); ``teacher_psnr`` is null.

Images. A JPEG file is stored byte for byte (the ground truth is not re-compressed); any other format is
decoded and stored as JPEG quality 92 (``protocol.JPEG_QUALITY``). Masks are all valid (255): every pixel
of a photograph is real, so the benchmark is measured over the full image (``OUT/benchmark.json``).

Output: ``OUT/test/shard-*.tar`` and ``index.json``, ``OUT/stats.json``, ``OUT/benchmark.json`` and
``OUT/stereonvs.json`` (per scene: sizes, K, scale, the pairs' spread, rectification angles, counts).
Everything is read and checked (every image decoded) before the old test shards of OUT are removed; OUT
must be new, empty or an earlier import holding only files it wrote (``common.ownership.check_replaceable``: a
build's folder, or a file of the user's added to an import, is refused), apart from ROOT.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenesplat_stereo.captured.colmap import image_size
from scenesplat_stereo.captured.llff import read_poses_bounds
from scenesplat_stereo.common.files import atomic_write_json
from scenesplat_stereo.common.ownership import OwnedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import format_table, key_safe_name, positive_number, whole_number
from scenesplat_stereo.scene.cameras import baseline_doubt, right_camera, rotation_angle_deg
from scenesplat_stereo.shards.benchmark_file import Benchmark, write_benchmark
from scenesplat_stereo.shards.encode import SampleImages, decode_image, encode_jpeg, encode_sample
from scenesplat_stereo.shards.sample import SampleMeta, sample_key
from scenesplat_stereo.shards.webdataset import ShardWriter, collect_stats, remove_unplanned, write_index, write_stats

SUBSET = "StereoNVS"
SPLIT = "test"
log = logging.getLogger(__name__)
OWNER = "scenesplat-stereo import stereonvs"  # recorded in OUT's manifest: a later import may replace OUT
REPORT_NAME = "stereonvs.json"
POSES_NAME = "poses_bounds.npy"
SCALE_TOLERANCE = 0.05  # relative spread of the pairs' scales around their median (not from the paper)
RECTIFICATION_TOLERANCE_DEG = 3.0  # rotation and baseline direction of a pair (not from the paper)
MAX_TARGETS = 100  # member names target_<jj> have two digits
PAPER_SCENES, PAPER_TARGETS = 8, 224  # paper section 5: "8 real-world scenes, 224 pairs"
PROTOCOL = ("StereoNVS-Real: every left frame a target once, its input the stereo pair with the nearest other "
            "left camera centre; full-image metrics")
_JPEG_SUFFIXES = (".jpg", ".jpeg")


class StereoNvsError(ValueError):
    """A StereoNVS folder that cannot be imported; the message names the file, scene or pair and the numbers."""


@dataclass(frozen=True)
class StereoNvsScene:
    """One scene as found on disk: ``name`` (key-safe folder name), its left and right image files in
    name order, their poses (OpenCV c2w [N, 4, 4], COLMAP units), the image size (W, H) in pixels, K
    (pixels, at that size) and poses_bounds' own image size (W, H)."""

    name: str
    folder: Path
    left: tuple[Path, ...]
    right: tuple[Path, ...]
    c2w_left: np.ndarray
    c2w_right: np.ndarray
    width: int
    height: int
    K: np.ndarray
    poses_size: tuple[int, int]


@dataclass(frozen=True)
class Calibration:
    """A scene's metric scale (metres per COLMAP unit) and what its pairs say: each pair's scale, the
    rotation between its cameras and its baseline's angle off the left camera's x axis (degrees)."""

    scale: float
    pair_scales: np.ndarray
    rotation_deg: np.ndarray
    direction_deg: np.ndarray


# ------------------------------------------------------------------------------------------ the protocol
def nearest_inputs(centres: np.ndarray) -> np.ndarray:
    """For each frame i of ``centres`` [N, 3] (N >= 2), the frame j != i with the nearest camera centre
    (ties: the lower j). Returns [N] int."""
    c = np.asarray(centres, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or len(c) < 2:
        raise ValueError(f"nearest_inputs: need centres [N >= 2, 3], got shape {c.shape}")
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return np.argmin(d, axis=1)  # the first minimum: the lower index on ties


def input_pairs(centres: np.ndarray) -> list[tuple[int, tuple[int, ...]]]:
    """The samples of a scene: (input frame j, the target frames that chose j, ascending), j ascending;
    every frame is a target exactly once and never its own input."""
    nearest = nearest_inputs(centres)
    return [(int(j), tuple(int(i) for i in np.flatnonzero(nearest == j))) for j in np.unique(nearest)]


def pair_scales(c2w_left: np.ndarray, c2w_right: np.ndarray, baseline: float) -> np.ndarray:
    """Metres per unit of each pair [N]: ``baseline`` (metres) over its camera-centre distance (inf when
    the two centres coincide)."""
    dist = np.linalg.norm(np.asarray(c2w_right)[:, :3, 3] - np.asarray(c2w_left)[:, :3, 3], axis=-1)
    with np.errstate(divide="ignore"):
        return np.where(dist > 0, baseline / np.where(dist > 0, dist, 1.0), np.inf)


def rectification_angles(c2w_left: np.ndarray, c2w_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair (degrees): the rotation between the two cameras, and the angle between the baseline
    C_R - C_L in the left camera's axes and its +x axis (0 for a rectified pair, 180 for a swapped one)."""
    left, right = np.asarray(c2w_left, dtype=np.float64), np.asarray(c2w_right, dtype=np.float64)
    d = np.einsum("nji,nj->ni", left[:, :3, :3], right[:, :3, 3] - left[:, :3, 3])
    norm = np.linalg.norm(d, axis=-1)
    cos = np.where(norm > 0, d[:, 0] / np.where(norm > 0, norm, 1.0), -1.0)
    return rotation_angle_deg(left, right), np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


# ------------------------------------------------------------------------------------------ reading
def find_scenes(root: Path, names: list[str] | None = None) -> list[Path]:
    """Scene folders of ``root`` (sub-folders holding ``poses_bounds.npy``), sorted; ``names`` picks some
    by folder name (each must exist)."""
    root = Path(root)
    if not root.is_dir():
        raise StereoNvsError(f"ROOT {root}: not a folder")
    found = sorted(p for p in root.iterdir()
                   if p.is_dir() and not p.name.startswith(".") and (p / POSES_NAME).is_file())
    if names:
        missing = sorted(set(names) - {p.name for p in found})
        if missing:
            raise StereoNvsError(f"--scenes: {missing} not found in {root} (scenes there: {[p.name for p in found]})")
        found = [p for p in found if p.name in set(names)]
    if not found:
        raise StereoNvsError(f"ROOT {root}: no scene folder with {POSES_NAME} (layout: ROOT/<scene>/{POSES_NAME}, "
                             "images/left/*, images/right/*)")
    return found


def _images(folder: Path) -> tuple[Path, ...]:
    if not folder.is_dir():
        raise StereoNvsError(f"{folder}: missing (StereoNVS layout: <scene>/images/left and images/right)")
    files = tuple(sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")))
    if not files:
        raise StereoNvsError(f"{folder}: no images")
    return files


def read_scene(folder: Path) -> StereoNvsScene:
    """One scene's files and cameras, checked: the same image names left and right, 2N poses for N pairs,
    one image size (read from every file's header). StereoNvsError (or LlffError) naming the file."""
    folder = Path(folder)
    left, right = _images(folder / "images" / "left"), _images(folder / "images" / "right")
    if [p.name for p in left] != [p.name for p in right]:
        i = next((k for k, (a, b) in enumerate(zip(left, right)) if a.name != b.name), min(len(left), len(right)))
        a = left[i].name if i < len(left) else "nothing"
        b = right[i].name if i < len(right) else "nothing"
        raise StereoNvsError(f"{folder}/images: left and right differ at image {i} in name order ({a} and {b}); "
                             f"{len(left)} left and {len(right)} right images")
    cams = read_poses_bounds(folder / POSES_NAME)
    n = len(left)
    if len(cams.c2w) != 2 * n:
        raise StereoNvsError(f"{folder / POSES_NAME}: {len(cams.c2w)} rows for {n} stereo pairs (expected 2N = "
                             f"{2 * n}: rows 0..N-1 left, N..2N-1 right)")
    if n < 2:
        raise StereoNvsError(f"{folder}: one stereo pair; a target needs another pair as its input")
    size = image_size(left[0])
    for p in left + right:
        if image_size(p) != size:
            raise StereoNvsError(f"{p}: {image_size(p)[0]}x{image_size(p)[1]} pixels, {left[0].name} has "
                                 f"{size[0]}x{size[1]} (one camera for all images)")
    try:
        name = key_safe_name(folder.name)
    except ValueError as e:
        raise StereoNvsError(f"{folder}: scene {e}") from None
    return StereoNvsScene(name, folder, left, right, cams.c2w[:n], cams.c2w[n:], size[0], size[1],
                          cams.intrinsics(size), (cams.width, cams.height))


def calibrate(scene: StereoNvsScene, baseline: float, scale_tolerance: float = SCALE_TOLERANCE,
              rectification_tolerance: float = RECTIFICATION_TOLERANCE_DEG) -> Calibration:
    """The scene's metric scale from ``baseline`` (metres) and the checks of the module docstring;
    StereoNvsError naming the scene, the worst pair and its numbers when a check fails."""
    scales = pair_scales(scene.c2w_left, scene.c2w_right, baseline)
    where = lambda i: f"{scene.folder}: pair {i} ({scene.left[i].name})"  # noqa: E731
    if not np.isfinite(scales).all():
        raise StereoNvsError(f"{where(int(np.argmax(~np.isfinite(scales))))}: the right camera centre coincides "
                             "with the left one (no baseline to scale by)")
    scale = float(np.median(scales))
    spread = np.abs(scales / scale - 1.0)
    i = int(np.argmax(spread))
    if spread[i] > scale_tolerance:
        raise StereoNvsError(f"{where(i)}: its baseline gives {scales[i]:.6g} m per unit, {spread[i]:.1%} off the "
                             f"scene's median {scale:.6g} (--scale-tolerance {scale_tolerance:g}); the pairs disagree "
                             "about the scale")
    rot, direction = rectification_angles(scene.c2w_left, scene.c2w_right)
    i = int(np.argmax(np.maximum(rot, direction)))
    if max(rot[i], direction[i]) > rectification_tolerance:
        raise StereoNvsError(f"{where(i)}: not rectified as the model needs (right = left moved along its own x "
                             f"axis, same orientation): the cameras are {rot[i]:.2f} deg apart and the baseline is "
                             f"{direction[i]:.2f} deg off the left x axis (--rectification-tolerance "
                             f"{rectification_tolerance:g} deg)")
    return Calibration(scale, scales, rot, direction)


# ------------------------------------------------------------------------------------------ samples
def scene_samples(scene: StereoNvsScene, calibration: Calibration, baseline: float) -> list[SampleMeta]:
    """The sample records of one scene (``input_pairs``), cameras in metres."""
    c2w = scene.c2w_left.copy()
    c2w[:, :3, 3] *= calibration.scale
    out = []
    for j, targets in input_pairs(c2w[:, :3, 3]):
        if len(targets) > MAX_TARGETS:
            raise StereoNvsError(f"{scene.folder}: pair {j} is the nearest of {len(targets)} frames; a sample "
                                 f"holds at most {MAX_TARGETS} targets")
        rho = float(np.linalg.norm(c2w[list(targets), :3, 3] - c2w[j, :3, 3], axis=-1).max())
        out.append(SampleMeta(key=sample_key(scene.name, j), scene=scene.name, subset=SUBSET, frame=j,
                              width=scene.width, height=scene.height, K=scene.K, baseline=float(baseline), rho=rho,
                              teacher_psnr=None, c2w_left=c2w[j], c2w_right=right_camera(c2w[j], baseline),
                              target_ids=tuple(range(len(targets))), targets=c2w[list(targets)],
                              target_frames=targets))
    return out


def image_as_jpeg(path: Path, size: tuple[int, int]) -> tuple[bytes, bool]:
    """An image file as JPEG bytes for a shard: a 3-channel JPEG as it is on disk, anything else decoded
    (grey repeated, alpha dropped) and encoded at quality 92. Returns (bytes, re-encoded?); StereoNvsError
    naming the file when it does not decode or is not ``size`` (W, H)."""
    data = Path(path).read_bytes()
    try:
        pixels = decode_image(data, Path(path).suffix or ".jpg")
    except ValueError as e:
        raise StereoNvsError(f"{path}: {e}") from None
    if pixels.shape[:2] != (size[1], size[0]) or pixels.shape[2] not in (1, 3, 4):
        raise StereoNvsError(f"{path}: decoded {pixels.shape}, expected {size[1]}x{size[0]} pixels with 1, 3 or 4 "
                             "channels")
    if Path(path).suffix.lower() in _JPEG_SUFFIXES and pixels.shape[2] == 3:
        return data, False
    rgb = np.repeat(pixels, 3, axis=2) if pixels.shape[2] == 1 else pixels[..., :3]
    return encode_jpeg(np.ascontiguousarray(rgb)), True


def sample_members(scene: StereoNvsScene, meta: SampleMeta) -> tuple[dict[str, bytes], int]:
    """The shard members of one sample (SPEC section 5) and how many of its images were re-encoded."""
    size = (scene.width, scene.height)
    files = [scene.left[meta.frame], scene.right[meta.frame]] + [scene.left[i] for i in meta.target_frames]
    images = [image_as_jpeg(p, size) for p in files]
    names = ["left.jpg", "right.jpg"] + [f"target_{j:02d}.jpg" for j in meta.target_ids]
    sample = SampleImages(key=meta.key, left=None, right=None, targets=None,
                          masks=np.ones((meta.num_targets, scene.height, scene.width), dtype=bool),
                          target_ids=meta.target_ids, meta=meta.to_json(),
                          jpegs={n: data for n, (data, _) in zip(names, images)})
    return encode_sample(sample), sum(again for _, again in images)


# ------------------------------------------------------------------------------------------ the import
def import_stereonvs(root: Path, out: Path, baseline: float, scenes: list[str] | None = None,
                     scale_tolerance: float = SCALE_TOLERANCE,
                     rectification_tolerance: float = RECTIFICATION_TOLERANCE_DEG, samples_per_shard: int = 64,
                     progress: bool = True) -> dict:
    """Import ROOT into OUT (module docstring) and return the report written to ``OUT/stereonvs.json``."""
    for flag, value in (("--baseline", baseline), ("--scale-tolerance", scale_tolerance),
                        ("--rectification-tolerance", rectification_tolerance)):
        if not (np.isfinite(value) and value > 0):
            raise StereoNvsError(f"{flag} {value}: must be a finite number > 0")
    if samples_per_shard < 1:
        raise StereoNvsError(f"--samples-per-shard {samples_per_shard}: must be >= 1")
    hint = "--baseline is in metres (StereoNVS-Real's rig: 0.12)"
    doubt = baseline_doubt(baseline, f"--baseline {baseline:g}", hint, hint)
    if doubt:
        log.warning(doubt)
    check_apart(out, "--out", {"ROOT": root}, replaced=True)
    out = check_replaceable(out, "--out", OWNER)  # new, empty, or an earlier import with no file of anyone else
    parsed = [read_scene(f) for f in find_scenes(root, scenes)]
    clash = sorted({s.name for s in parsed if sum(t.name == s.name for t in parsed) > 1})
    if clash:
        raise StereoNvsError(f"ROOT {root}: scene folders {clash} give the same sample-key name; rename one")
    plans = []
    for scene in parsed:
        calibration = calibrate(scene, baseline, scale_tolerance, rectification_tolerance)
        plans.append((scene, calibration, scene_samples(scene, calibration, baseline)))
    images = [(s, p) for s, _, _ in plans for p in s.left + s.right]
    for scene, path in tqdm(images, desc="check images", unit="image", disable=not progress):
        image_as_jpeg(path, (scene.width, scene.height))  # every image decodes, before OUT is touched
    report = {"root": str(Path(root).resolve()), "baseline": baseline, "scale_tolerance": scale_tolerance,
              "rectification_tolerance_deg": rectification_tolerance, "reencoded_images": 0,
              "paper": {"scenes": PAPER_SCENES, "targets": PAPER_TARGETS}, "scenes": []}
    total = sum(len(samples) for _, _, samples in plans)
    with OwnedFolder(out, OWNER):  # every file it holds is recorded as this import's, however it ends
        remove_unplanned(out, SPLIT, set())  # the test shards of an earlier import
        with ShardWriter(out, SPLIT, samples_per_shard) as writer, \
                tqdm(total=total, desc="test shards", unit="pair", disable=not progress) as bar:
            for scene, calibration, samples in plans:
                for meta in samples:
                    members, again = sample_members(scene, meta)
                    writer.add(meta.key, members)
                    report["reencoded_images"] += again
                    bar.update()
                report["scenes"].append(_scene_row(scene, calibration, samples))
        write_index(out, SPLIT)
        write_stats(out, collect_stats(out))
        write_benchmark(out, Benchmark(masked=False, source="captured", protocol=PROTOCOL))
        atomic_write_json(Path(out) / REPORT_NAME, report)
    return report


def _scene_row(scene: StereoNvsScene, calibration: Calibration, samples: list[SampleMeta]) -> dict:
    spread = np.abs(calibration.pair_scales / calibration.scale - 1.0)
    return {"scene": scene.name, "folder": str(scene.folder), "frames": len(scene.left),
            "image_size": [scene.width, scene.height], "poses_bounds_size": list(scene.poses_size),
            "K": scene.K.tolist(), "scale_m_per_unit": calibration.scale, "scale_spread": float(spread.max()),
            "max_rotation_deg": float(calibration.rotation_deg.max()),
            "max_baseline_angle_deg": float(calibration.direction_deg.max()),
            "pairs": len(samples), "targets": sum(m.num_targets for m in samples)}


def summary_table(report: dict) -> str:
    """One line per scene (frames, image size, fx/fy, scale, the checks, stored pairs and targets), the
    total, and the paper's counts beside it."""
    rows = [("scene", "frames", "size", "fx", "fy", "m/unit", "spread", "rot deg", "dir deg", "pairs", "targets")]
    for r in report["scenes"]:
        rows.append((r["scene"], r["frames"], "x".join(map(str, r["image_size"])), f"{r['K'][0][0]:.1f}",
                     f"{r['K'][1][1]:.1f}", f"{r['scale_m_per_unit']:.5g}", f"{r['scale_spread']:.2%}",
                     f"{r['max_rotation_deg']:.2f}", f"{r['max_baseline_angle_deg']:.2f}", r["pairs"], r["targets"]))
    scenes = report["scenes"]
    rows.append((f"total {len(scenes)}", sum(r["frames"] for r in scenes), "", "", "", "", "", "", "",
                 sum(r["pairs"] for r in scenes), sum(r["targets"] for r in scenes)))
    paper = report["paper"]
    return (format_table(rows, rule=True) + f"\npaper (section 5): {paper['scenes']} scenes, {paper['targets']} "
            f"stereo-to-target pairs = targets; re-encoded images: {report['reencoded_images']}")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("root", type=Path, metavar="ROOT", help="StereoNVS-Real folder: ROOT/<scene>/images/{left,right}/*, "
                   "ROOT/<scene>/poses_bounds.npy (e.g. StereoNeRF's validation folder of 8 scenes)")
    p.add_argument("--out", type=Path, required=True, help="output folder (OUT/test/shard-*.tar, index.json, "
                   "stats.json, benchmark.json, stereonvs.json): new, or an earlier import (replaced); never a build")
    p.add_argument("--baseline", type=positive_number("--baseline"), required=True,
                   help="the stereo rig's baseline in metres: fixes the scale of the COLMAP poses")
    p.add_argument("--scenes", type=lambda t: [s for s in t.split(",") if s], metavar="A,B,...",
                   help="import only these scene folders (default: every folder with poses_bounds.npy)")
    p.add_argument("--scale-tolerance", type=positive_number("--scale-tolerance"), default=SCALE_TOLERANCE,
                   help=f"refuse a scene whose pairs' scales differ from their median by more than this fraction "
                        f"(default {SCALE_TOLERANCE})")
    p.add_argument("--rectification-tolerance", type=positive_number("--rectification-tolerance"),
                   default=RECTIFICATION_TOLERANCE_DEG, metavar="DEG",
                   help="refuse a scene with a pair whose cameras turn, or whose baseline leaves the left x axis, by "
                        f"more than this many degrees (default {RECTIFICATION_TOLERANCE_DEG:g})")
    p.add_argument("--samples-per-shard", type=whole_number("--samples-per-shard"), default=64,
                   help="samples (input pairs) per tar (default 64)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    """CLI entry: import and print the summary. A refused input raises (OUT is then untouched);
    ``commandline.run_command`` makes it one line naming the file or flag, and exit 2."""
    report = import_stereonvs(args.root, args.out, args.baseline, args.scenes, args.scale_tolerance,
                              args.rectification_tolerance, args.samples_per_shard, not args.no_progress)
    print(summary_table(report))
    return 0
