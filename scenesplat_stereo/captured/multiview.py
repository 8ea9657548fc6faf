"""``scenesplat-stereo import multiview``: rectified multi-view line sets (views taken along one horizontal
line, such as the nine-view Middlebury 2001 sets) as test shards (SPEC section 5) that ``sgmodel eval`` reads.

Input, one folder per set under ROOT (or ROOT itself when it holds the views):

    ROOT/<set>/im0.<ext> .. im<N-1>.<ext>   the views, numbered left to right along the line, all one size
    ROOT/<set>/disp<L>.png                  optional: ground-truth disparity of view L (the stereo pair's left
                                            view) against view R, times ``--disparity-scale``; 0 = unknown

Cameras. Such sets carry no calibration; any focal length and baseline give the same images for views on
the line, so the user states a plausible metric pair: ``--focal`` fx = fy (pixels, principal point at the
image centre, pixel centres at +0.5) and ``--baseline`` B (metres) between the pair's views L and R
(``--pair L,R``). View k sits at x = p_k B along the left camera's +x axis (to its right), same orientation,
with p_k from ``--view-positions`` (one number per view, in units of B, p_L = 0 and p_R = 1, increasing
left to right) or, by default, evenly spaced: p_k = (k - L) / (R - L). World = the left camera (c2w_left = I,
OpenCV axes, metres); c2w_right = Trans(B, 0, 0); target k: Trans(p_k B, 0, 0).

Protocol. One sample per set: input (view L, view R), every other view a target (``target_frames`` = the
view numbers, ascending; ``target_ids`` 0..T-1), labelled "between" when 0 < p_k < 1 and "beside" otherwise
(``target_groups``; ``sgmodel eval`` reports each group). ``rho`` is the farthest target's distance (metres);
``teacher_psnr`` is null. Key ``<set>__<L:06d>``.

Masks (``mask_<jj>.png``). With ``disp<L>.png``: a target pixel is valid when the left view sees it with a
known disparity. Along a rectified line a left pixel centre x (row y) with disparity d (pixels between L and
R) lands at x - p_k d in view k, on the same row; each landing marks its target pixel, and the span between
two horizontal neighbours of known disparity that differ by at most ``SURFACE_STEP`` px (one surface, not
an occlusion edge) marks the target pixels whose centres it covers. Without the file every pixel is valid.
The set is a photograph, so its benchmark.json says full-image metrics (``masked: false``); ``sgmodel eval``
reports both.

Checks, before OUT is touched (one line naming the file or flag, exit 2): views numbered 0..N-1 without gaps
or repeats, every view decodes at one size, the pair present and L < R, the positions (count, p_L = 0, p_R =
1, increasing), the focal length (a horizontal field of view of ``FOV_RANGE_DEG`` degrees), the baseline
(above ``cameras.LONG_BASELINE`` metres is refused as millimetres or centimetres), the disparity map (its
size, a single channel, its known values in 0 < d < W pixels).

Images. A 3-channel JPEG is stored byte for byte, anything else (PNG, PPM) decoded and stored as JPEG quality
92 (``stereonvs.image_as_jpeg``). Output: ``OUT/test/shard-*.tar``, ``index.json``, ``OUT/stats.json``,
``OUT/benchmark.json`` and ``OUT/multiview.json`` (per set: size, K, baseline, positions, groups, valid
fractions). OUT must be new, empty or an earlier import holding only this command's files
(``common.ownership.check_replaceable``).
"""

from __future__ import annotations

import argparse
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenesplat_stereo.captured.colmap import image_size
from scenesplat_stereo.captured.stereonvs import image_as_jpeg
from scenesplat_stereo.common.files import atomic_write_json
from scenesplat_stereo.common.ownership import OwnedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import argtype, format_table, key_safe_name, parse_number, positive_number
from scenesplat_stereo.scene.cameras import LONG_BASELINE, intrinsics_matrix, translation
from scenesplat_stereo.shards.benchmark_file import Benchmark, write_benchmark
from scenesplat_stereo.shards.encode import SampleImages, decode_image, encode_sample
from scenesplat_stereo.shards.sample import SampleMeta, sample_key
from scenesplat_stereo.shards.webdataset import ShardWriter, collect_stats, remove_unplanned, write_index, write_stats

SUBSET = "multiview"
SPLIT = "test"
OWNER = "scenesplat-stereo import multiview"  # recorded in OUT's manifest: a later import may replace OUT
REPORT_NAME = "multiview.json"
DEFAULT_PAIR = (2, 6)  # the Middlebury 2001 sets' ground-truth pair
DEFAULT_DISPARITY_SCALE = 8.0  # Middlebury 2001: disp<L>.png holds 8 x the disparity in pixels
FOV_RANGE_DEG = (5.0, 170.0)  # plausible horizontal fields of view for --focal (not from the paper)
SURFACE_STEP = 1.0  # px: neighbours whose disparities differ by more are an occlusion edge (not from the paper)
MAX_TARGETS = 100  # member names target_<jj> have two digits
BETWEEN, BESIDE = "between", "beside"
PROTOCOL = ("rectified multi-view line: the stereo pair in, every other view a target (between / beside the "
            "pair); full-image metrics, masks = target pixels the left view sees with known disparity")
_VIEW_RE = re.compile(r"^im(\d+)\.[A-Za-z0-9]+$")


class MultiviewError(ValueError):
    """A multi-view set or flag that cannot be imported; the message names the file or flag and the numbers."""


@dataclass(frozen=True)
class LineSet:
    """One set as found on disk: ``name`` (key-safe folder name), its view files by number (0..N-1), the
    image size (W, H) in pixels and the left view's disparity file (None when absent)."""

    name: str
    folder: Path
    views: tuple[Path, ...]
    width: int
    height: int
    disparity: Path | None


# ------------------------------------------------------------------------------------------ geometry
def view_positions(count: int, pair: tuple[int, int], positions: list[float] | None = None) -> np.ndarray:
    """p_k of each of ``count`` views in units of the pair's baseline (module docstring), checked: the pair
    in range with L < R; given ``positions``: one per view, finite, p_L = 0, p_R = 1, strictly increasing.
    MultiviewError naming the flag."""
    left, right = pair
    if not 0 <= left < right < count:
        raise MultiviewError(f"--pair {left},{right}: need 0 <= L < R < {count} (the set has views 0..{count - 1}; "
                             "L is the left view of the stereo pair)")
    if positions is None:
        return (np.arange(count, dtype=np.float64) - left) / (right - left)
    p = np.asarray(positions, dtype=np.float64)
    if p.shape != (count,) or not np.isfinite(p).all():
        raise MultiviewError(f"--view-positions: {len(positions)} numbers for {count} views (one finite number each)")
    if p[left] != 0.0 or p[right] != 1.0:
        raise MultiviewError(f"--view-positions: view {left} (L) must be at 0 and view {right} (R) at 1 (units of "
                             f"the baseline), got {p[left]:g} and {p[right]:g}")
    if not (np.diff(p) > 0).all():
        k = int(np.argmax(np.diff(p) <= 0))
        raise MultiviewError(f"--view-positions: views are numbered left to right, but view {k + 1} ({p[k + 1]:g}) "
                             f"is not right of view {k} ({p[k]:g})")
    return p


def check_focal(focal: float, width: int, where: str) -> None:
    """MultiviewError when ``focal`` (pixels) gives a horizontal field of view outside ``FOV_RANGE_DEG`` on an
    image ``width`` pixels wide (a focal length for another image size, or in millimetres)."""
    fov = math.degrees(2 * math.atan(width / (2 * focal)))
    low, high = FOV_RANGE_DEG
    if not low <= fov <= high:
        raise MultiviewError(f"--focal {focal:g}: a {fov:.1f} deg horizontal field of view on {where} ({width} px "
                             f"wide); expected {low:g}..{high:g} deg: is it in pixels of these images?")


def check_baseline(baseline: float) -> None:
    """MultiviewError for a baseline (metres) that is not > 0 or longer than ``LONG_BASELINE``."""
    if not (math.isfinite(baseline) and 0 < baseline <= LONG_BASELINE):
        raise MultiviewError(f"--baseline {baseline:g}: expected metres, 0 < B <= {LONG_BASELINE:g} (a longer one is "
                             "likely millimetres or centimetres)")


def target_masks(disparity: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Valid masks [T, H, W] bool of targets at ``positions`` [T] (units of the baseline) from the left view's
    disparity [H, W] (pixels against the view at 1; 0 or less = unknown), as the module docstring says."""
    d = np.asarray(disparity, dtype=np.float64)
    h, w = d.shape
    known = d > 0
    pair = known[:, :-1] & known[:, 1:] & (np.abs(d[:, 1:] - d[:, :-1]) <= SURFACE_STEP)
    rows = np.arange(h)[:, None]
    out = np.zeros((len(positions), h, w), dtype=bool)
    for t, p in enumerate(positions):
        x = np.arange(w)[None, :] + 0.5 - p * d                         # landing of each left pixel centre
        hit = np.floor(x).astype(np.int64)
        inside = known & (hit >= 0) & (hit < w)
        out[t][np.broadcast_to(rows, (h, w))[inside], hit[inside]] = True
        # spans: target pixel centres c + 0.5 within [min, max] of two neighbours' landings
        lo = np.minimum(x[:, :-1], x[:, 1:])[pair]
        hi = np.maximum(x[:, :-1], x[:, 1:])[pair]
        first = np.clip(np.ceil(lo - 0.5), 0, w).astype(np.int64)
        last = np.clip(np.floor(hi - 0.5) + 1, 0, w).astype(np.int64)    # exclusive
        ok = last > first
        diff = np.zeros((h, w + 1), dtype=np.int64)
        r = np.broadcast_to(rows, pair.shape)[pair][ok]
        np.add.at(diff, (r, first[ok]), 1)
        np.add.at(diff, (r, last[ok]), -1)
        out[t] |= np.cumsum(diff, axis=1)[:, :w] > 0
    return out


# ------------------------------------------------------------------------------------------ reading
def find_sets(root: Path) -> list[Path]:
    """ROOT itself when it holds ``im0.*``, else its sub-folders that do, sorted."""
    root = Path(root)
    if not root.is_dir():
        raise MultiviewError(f"ROOT {root}: not a folder")
    holds = lambda f: any(_VIEW_RE.match(p.name) and p.stem == "im0" for p in f.iterdir())  # noqa: E731
    if holds(root):
        return [root]
    found = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and holds(p))
    if not found:
        raise MultiviewError(f"ROOT {root}: no set (layout: ROOT/<set>/im0.png .. im<N-1>.png, or ROOT/im0.png ..)")
    return found


def read_set(folder: Path, left: int) -> LineSet:
    """One set's views (numbered 0..N-1, one file each, one size) and its ``disp<left>.png``; MultiviewError
    naming the file."""
    folder = Path(folder)
    numbered: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        m = _VIEW_RE.match(p.name)
        if m and p.is_file():
            k = int(m.group(1))
            if k in numbered:
                raise MultiviewError(f"{p}: view {k} is also {numbered[k].name} (one file per view)")
            numbered[k] = p
    missing = sorted(set(range(max(numbered) + 1)) - set(numbered))
    if missing:
        raise MultiviewError(f"{folder}: views {missing} missing (views are im0 .. im{max(numbered)}, no gaps)")
    views = tuple(numbered[k] for k in range(len(numbered)))
    if len(views) < 3:
        raise MultiviewError(f"{folder}: {len(views)} views; a pair and at least one target need 3")
    size = _size(views[0])
    for p in views[1:]:
        if _size(p) != size:
            raise MultiviewError(f"{p}: {_size(p)[0]}x{_size(p)[1]} pixels, {views[0].name} has {size[0]}x{size[1]} "
                                 "(one camera for all views)")
    disparity = folder / f"disp{left}.png"
    try:
        name = key_safe_name(folder.name)
    except ValueError as e:
        raise MultiviewError(f"{folder}: set {e}") from None
    return LineSet(name, folder, views, size[0], size[1], disparity if disparity.is_file() else None)


def _size(path: Path) -> tuple[int, int]:
    try:
        return image_size(path)
    except ValueError as e:
        raise MultiviewError(str(e)) from None


def read_disparity(path: Path, size: tuple[int, int], scale: float) -> np.ndarray:
    """``disp<L>.png`` [H, W] as pixels (stored value / ``scale``; 0 = unknown), checked: one channel, the
    views' size (W, H), known values below the image width. MultiviewError naming the file."""
    try:
        raw = decode_image(Path(path).read_bytes(), ".png")
    except ValueError as e:
        raise MultiviewError(f"{path}: {e}") from None
    if raw.shape != (size[1], size[0], 1):
        raise MultiviewError(f"{path}: decoded {raw.shape}, expected one channel of {size[1]}x{size[0]} pixels (the "
                             "views' size)")
    d = raw[..., 0].astype(np.float64) / scale
    if not (d > 0).any():
        raise MultiviewError(f"{path}: no known disparity (every pixel 0)")
    if d.max() >= size[0]:
        raise MultiviewError(f"{path}: disparity {d.max():g} px (stored / --disparity-scale {scale:g}) is not below the "
                             f"image width {size[0]}: is --disparity-scale right?")
    return d


# ------------------------------------------------------------------------------------------ samples
def set_sample(line: LineSet, focal: float, baseline: float, pair: tuple[int, int], p: np.ndarray) -> SampleMeta:
    """The one sample record of a set (module docstring), cameras in metres."""
    left, right = pair
    frames = tuple(k for k in range(len(line.views)) if k not in pair)
    if len(frames) > MAX_TARGETS:
        raise MultiviewError(f"{line.folder}: {len(frames)} targets; a sample holds at most {MAX_TARGETS}")
    K = intrinsics_matrix(focal, focal, line.width / 2, line.height / 2)
    x = p[list(frames)] * baseline
    return SampleMeta(key=sample_key(line.name, left), scene=line.name, subset=SUBSET, frame=left,
                      width=line.width, height=line.height, K=K, baseline=float(baseline),
                      rho=float(np.abs(x).max()), teacher_psnr=None, c2w_left=np.eye(4),
                      c2w_right=translation(np.array([baseline, 0.0, 0.0])), target_ids=tuple(range(len(frames))),
                      targets=np.stack([translation(np.array([v, 0.0, 0.0])) for v in x]), target_frames=frames,
                      target_groups=tuple(BETWEEN if 0 < p[k] < 1 else BESIDE for k in frames))


def sample_members(line: LineSet, meta: SampleMeta, right: int, masks: np.ndarray) -> tuple[dict[str, bytes], int]:
    """The shard members of a set's sample (SPEC section 5; ``right`` the pair's right view, ``masks`` [T, H, W])
    and how many of its images were re-encoded."""
    files = [line.views[meta.frame], line.views[right]] + [line.views[k] for k in meta.target_frames]
    images = [image_as_jpeg(f, (line.width, line.height)) for f in files]
    names = ["left.jpg", "right.jpg"] + [f"target_{j:02d}.jpg" for j in meta.target_ids]
    sample = SampleImages(key=meta.key, left=None, right=None, targets=None, masks=masks,
                          target_ids=meta.target_ids, meta=meta.to_json(),
                          jpegs={n: data for n, (data, _) in zip(names, images)})
    return encode_sample(sample), sum(again for _, again in images)


@dataclass(frozen=True)
class Plan:
    """What one set becomes: its files, the sample record, the target masks and what the report says."""

    line: LineSet
    meta: SampleMeta
    masks: np.ndarray
    positions: np.ndarray


def plan_set(folder: Path, focal: float, baseline: float, pair: tuple[int, int], positions: list[float] | None,
             disparity_scale: float) -> Plan:
    """Read and check one set and plan its sample (every view decodes); MultiviewError naming file or flag."""
    line = read_set(folder, pair[0])
    p = view_positions(len(line.views), pair, positions)
    check_focal(focal, line.width, str(line.views[0]))
    meta = set_sample(line, focal, baseline, pair, p)
    for view in line.views:
        image_as_jpeg(view, (line.width, line.height))  # decodes at the stated size, before OUT is touched
    if line.disparity is None:
        masks = np.ones((meta.num_targets, line.height, line.width), dtype=bool)
    else:
        d = read_disparity(line.disparity, (line.width, line.height), disparity_scale)
        masks = target_masks(d, p[list(meta.target_frames)])
    return Plan(line, meta, masks, p)


def import_multiview(root: Path, out: Path, focal: float, baseline: float, pair: tuple[int, int] = DEFAULT_PAIR,
                     positions: list[float] | None = None, disparity_scale: float = DEFAULT_DISPARITY_SCALE) -> dict:
    """Import ROOT into OUT (module docstring) and return the report written to ``OUT/multiview.json``."""
    check_baseline(baseline)
    for flag, value in (("--focal", focal), ("--disparity-scale", disparity_scale)):
        if not (math.isfinite(value) and value > 0):
            raise MultiviewError(f"{flag} {value}: must be a finite number > 0")
    plans = [plan_set(f, focal, baseline, pair, positions, disparity_scale) for f in find_sets(root)]
    clash = sorted({p.line.name for p in plans if sum(q.line.name == p.line.name for q in plans) > 1})
    if clash:
        raise MultiviewError(f"ROOT {root}: set folders {clash} give the same sample-key name; rename one")
    check_apart(out, "--out", {"ROOT": root}, replaced=True)
    out = check_replaceable(out, "--out", OWNER)  # new, empty, or an earlier import with no file of anyone else
    rows, reencoded = [], 0
    with OwnedFolder(out, OWNER):  # every file it holds is recorded as this import's, however it ends
        remove_unplanned(out, SPLIT, set())  # the test shards of an earlier import
        with ShardWriter(out, SPLIT, len(plans)) as writer:
            for plan in plans:
                members, again = sample_members(plan.line, plan.meta, pair[1], plan.masks)
                writer.add(plan.meta.key, members)
                reencoded += again
                rows.append(_set_row(plan))
        write_index(out, SPLIT)
        write_stats(out, collect_stats(out))
        write_benchmark(out, Benchmark(masked=False, source="captured", protocol=PROTOCOL))
        report = {"root": str(Path(root).resolve()), "focal_px": focal, "baseline_m": baseline, "pair": list(pair),
                  "view_positions": positions, "disparity_scale": disparity_scale, "reencoded_images": reencoded,
                  "sets": rows}
        atomic_write_json(Path(out) / REPORT_NAME, report)
    return report


def _set_row(plan: Plan) -> dict:
    meta = plan.meta
    return {"set": plan.line.name, "folder": str(plan.line.folder), "views": len(plan.line.views),
            "image_size": [plan.line.width, plan.line.height], "K": meta.K.tolist(),
            "positions": plan.positions.tolist(), "target_views": list(meta.target_frames),
            "groups": list(meta.target_groups), "disparity": str(plan.line.disparity) if plan.line.disparity else None,
            "valid_fraction": [round(float(m.mean()), 6) for m in plan.masks]}


def summary_table(report: dict) -> str:
    """One line per set: views, size, fx, the targets between and beside the pair, their mean valid fraction."""
    rows = [("set", "views", "size", "fx", "between", "beside", "valid", "disparity")]
    for r in report["sets"]:
        groups = r["groups"]
        rows.append((r["set"], r["views"], "x".join(map(str, r["image_size"])), f"{r['K'][0][0]:.1f}",
                     ",".join(str(k) for k, g in zip(r["target_views"], groups) if g == BETWEEN),
                     ",".join(str(k) for k, g in zip(r["target_views"], groups) if g == BESIDE),
                     f"{np.mean(r['valid_fraction']):.1%}", "yes" if r["disparity"] else "no (masks all valid)"))
    return (format_table(rows, rule=True) + f"\npair {report['pair'][0]},{report['pair'][1]}, baseline "
            f"{report['baseline_m']:g} m; re-encoded images: {report['reencoded_images']}")


def _pair(text: str, flag: str) -> tuple[int, int]:
    parts = str(text).split(",")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ValueError(f"{flag} {text!r}: expected two view numbers L,R (e.g. 2,6)")
    return int(parts[0]), int(parts[1])


def _numbers(text: str, flag: str) -> list[float]:
    return [parse_number(v.strip(), flag, float) for v in str(text).split(",")]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("root", type=Path, metavar="ROOT", help="a set folder (im0.png .. im<N-1>.png, optional "
                   "disp<L>.png) or a folder of them")
    p.add_argument("--out", type=Path, required=True, help="output folder (OUT/test/shard-*.tar, index.json, "
                   "stats.json, benchmark.json, multiview.json): new, or an earlier import (replaced); never a build")
    p.add_argument("--focal", type=positive_number("--focal"), required=True,
                   help="fx = fy in pixels of the views (principal point at the centre), e.g. 450")
    p.add_argument("--baseline", type=positive_number("--baseline"), required=True,
                   help=f"metres between the pair's views L and R (e.g. 0.065; at most {LONG_BASELINE:g})")
    p.add_argument("--pair", type=argtype(_pair, "--pair"), default=DEFAULT_PAIR, metavar="L,R",
                   help=f"the stereo input's left and right view numbers (default {DEFAULT_PAIR[0]},{DEFAULT_PAIR[1]}, "
                        "the Middlebury 2001 pair)")
    p.add_argument("--view-positions", type=argtype(_numbers, "--view-positions"), metavar="P0,P1,...",
                   help="each view's position along the line in units of the baseline, L at 0 and R at 1 (default: "
                        "evenly spaced, (k - L) / (R - L))")
    p.add_argument("--disparity-scale", type=positive_number("--disparity-scale"), default=DEFAULT_DISPARITY_SCALE,
                   help=f"disp<L>.png holds this times the disparity in pixels (default {DEFAULT_DISPARITY_SCALE:g}, "
                        "Middlebury 2001)")


def run(args: argparse.Namespace) -> int:
    """CLI entry: import and print the summary. A refused input raises (OUT is then untouched);
    ``commandline.run_command`` makes it one line naming the file or flag, and exit 2."""
    report = import_multiview(args.root, args.out, args.focal, args.baseline, args.pair, args.view_positions,
                              args.disparity_scale)
    print(summary_table(report))
    return 0
