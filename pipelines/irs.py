"""IRS pose recovery (paper appendix F, "IRS camera reconstruction"; SPEC section 6).

IRS ships rectified stereo sequences without camera poses. Each scene variant (a folder of ``l_<n>.png``,
``r_<n>.png`` and ``d_<n>.exr``) is reconstructed on its own with COLMAP from its left images, intrinsics
fixed at fx = fy = 480, (cx, cy) = (480, 270) for 960x540; the largest reconstruction is kept; its metric
scale is the median over matched sparse points of (ground-truth depth z = 48 / d) / (reconstructed depth);
right-camera poses follow from the rectified 0.1 m baseline; a variant is kept when it has >= 150
registered frames, a mean reprojection error <= 1.5 px and a scale-ratio IQR <= 25% of its median.

Conventions: c2w 4x4 in OpenCV axes (x right, y down, z forward), metres. Disparity ``d`` is in pixels at
the native IRS width (960 px) whatever the image size handed to the pipeline, so z = fx B / d = 48 / d in
metres holds for reduced copies too (their intrinsics are scaled, the disparity is not). Observation pixel
(x, y) (pixel-centre convention of SPEC section 1) reads the disparity of pixel (floor(x), floor(y)).

Outputs per variant, in ``OUT/<variant>/``: ``poses.json`` (when a metric scale exists) and
``report.json`` (always; its presence marks the variant done, so reruns skip it); for the dataset,
``OUT/summary.json`` and a summary table (``run_dataset``).
"""

from __future__ import annotations

import os
import re
import shutil
import time
import traceback
from collections import Counter
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from scenesplat_stereo.captured.colmap import PinholeCamera, Recovery, RecoveryOptions, image_size, recover_poses
from scenesplat_stereo.common.commandline import quiet_worker_interrupts
from scenesplat_stereo.common.files import atomic_write_json
from scenesplat_stereo.common.text import format_table, key_safe_name
from scenesplat_stereo.scene.cameras import right_camera

# Paper appendix F: IRS intrinsics (pixels) at its native 960x540, and the rectified stereo baseline.
IRS_CAMERA = PinholeCamera(fx=480.0, fy=480.0, cx=480.0, cy=270.0, width=960, height=540)
IRS_BASELINE = 0.1  # metres
# Paper appendix F: depth from disparity, z = 48 / d (fx B = 480 px * 0.1 m, d in pixels at 960 px width).
IRS_FOCAL_BASELINE = 48.0
# Paper appendix F: the three quality filters of a reconstructed variant.
MIN_REGISTERED_FRAMES = 150
MAX_MEAN_REPROJECTION_ERROR = 1.5  # pixels
MAX_SCALE_IQR_FRACTION = 0.25  # IQR of the scale ratios / their median

_LEFT_RE = re.compile(r"^l_(\d+)\.png$")


@dataclass(frozen=True)
class Filters:
    """The quality filters of appendix F (defaults are the paper's; tests with reduced sizes lower
    ``min_registered``)."""

    min_registered: int = MIN_REGISTERED_FRAMES
    max_reprojection_error: float = MAX_MEAN_REPROJECTION_ERROR
    max_scale_iqr_fraction: float = MAX_SCALE_IQR_FRACTION


@dataclass(frozen=True)
class IrsFrame:
    """One stereo frame of a variant: frame number ``n`` and its left, right and disparity files."""

    n: int
    left: Path
    right: Path
    disparity: Path


@dataclass
class IrsVariant:
    """A scene variant: ``name`` (its path under the dataset root, '/' replaced by '-'), its folder, the
    frames with all three files, in frame-number order, and ``problems`` (counts of frames left out, by
    reason)."""

    name: str
    path: Path
    frames: list[IrsFrame]
    problems: Counter = field(default_factory=Counter)


def variant_name(root: Path, folder: Path) -> str:
    """Variant name from its folder: the path relative to the dataset root with '/' -> '-' (a variant at
    the root itself is named after the root folder), made usable in sample keys by ``text.key_safe_name``
    (no '.', whitespace or '__')."""
    rel = Path(folder).relative_to(Path(root))
    return key_safe_name("-".join(rel.parts) if rel.parts else Path(root).resolve().name)


def find_variants(root: Path) -> list[Path]:
    """Folders under ``root`` (itself included, symbolic links followed) holding at least one
    ``l_<n>.png``, sorted."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"IRS dataset root {root} is not a folder")
    return sorted(Path(d) for d, _, files in os.walk(root, followlinks=True)
                  if any(_LEFT_RE.match(f) for f in files))


def scan_variant(root: Path, folder: Path) -> IrsVariant:
    """List the frames of one variant; frames missing their right image or disparity are left out and
    counted in ``problems`` ("missing right image", "missing disparity")."""
    folder = Path(folder)
    variant = IrsVariant(variant_name(root, folder), folder, [])
    numbers = sorted(int(m.group(1)) for p in folder.iterdir() if (m := _LEFT_RE.match(p.name)))
    for n in numbers:
        right, disparity = folder / f"r_{n}.png", folder / f"d_{n}.exr"
        if not right.is_file():
            variant.problems["missing right image"] += 1
        elif not disparity.is_file():
            variant.problems["missing disparity"] += 1
        else:
            variant.frames.append(IrsFrame(n, folder / f"l_{n}.png", right, disparity))
    return variant


def check_sizes(variant: IrsVariant, camera: PinholeCamera) -> None:
    """Leave out (and count in ``problems``) frames with an unreadable file or a left image, right image
    or disparity whose size is not the camera's."""
    kept = []
    for f in variant.frames:
        try:
            sizes = {image_size(p) for p in (f.left, f.right, f.disparity)}
        except ValueError:
            variant.problems["unreadable file"] += 1
            continue
        if sizes != {(camera.width, camera.height)}:
            variant.problems["wrong image size"] += 1
            continue
        kept.append(f)
    variant.frames = kept


def read_disparity(path: Path) -> np.ndarray:
    """Disparity map [H, W] float32 in pixels (at the native IRS width) from an EXR, first channel
    (IRS files hold one channel or three equal ones). ValueError naming the file if unreadable."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    pixels = buf.get_pixels(oiio.FLOAT)
    if buf.has_error or pixels is None or pixels.ndim != 3:
        raise ValueError(f"{path}: cannot read disparity ({buf.geterror() or 'no pixels'})")
    return np.ascontiguousarray(pixels[..., 0], dtype=np.float32)


def depth_from_disparity(disparity: np.ndarray, focal_baseline: float = IRS_FOCAL_BASELINE) -> np.ndarray:
    """Depth z = focal_baseline / d in metres; NaN where d is not finite and positive."""
    d = np.asarray(disparity, dtype=np.float64)
    out = np.full(d.shape, np.nan)
    ok = np.isfinite(d) & (d > 0)
    out[ok] = focal_baseline / d[ok]
    return out


@dataclass
class ScaleEstimate:
    """Metric scale (metres per reconstruction unit): median and IQR (q75 - q25) of the per-observation
    ratios z_gt / z_rec; ``used`` ratios, ``invalid`` observations left out (disparity missing, not finite
    or <= 0, or a point behind the camera)."""

    median: float
    iqr: float
    used: int
    invalid: int


def metric_scale(recovery: Recovery, frames: list[IrsFrame],
                 focal_baseline: float = IRS_FOCAL_BASELINE) -> ScaleEstimate:
    """Scale ratios over every observation of every registered image of ``recovery`` (``frames`` indexed
    like the images given to COLMAP)."""
    ratios, invalid = [], 0
    for index, obs in zip(recovery.indices, recovery.observations):
        if len(obs.depth) == 0:
            continue
        depth = depth_from_disparity(read_disparity(frames[index].disparity), focal_baseline)
        h, w = depth.shape
        u = np.clip(np.floor(obs.xy[:, 0]).astype(np.int64), 0, w - 1)
        v = np.clip(np.floor(obs.xy[:, 1]).astype(np.int64), 0, h - 1)
        z_gt = depth[v, u]
        ok = np.isfinite(z_gt) & (obs.depth > 0)
        invalid += int((~ok).sum())
        ratios.append(z_gt[ok] / obs.depth[ok])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    if len(r) == 0:
        return ScaleEstimate(float("nan"), float("nan"), 0, invalid)
    q25, q50, q75 = np.percentile(r, [25, 50, 75])
    return ScaleEstimate(float(q50), float(q75 - q25), len(r), invalid)


def filter_reasons(registered: int, reprojection_error: float, scale: ScaleEstimate | None,
                   filters: Filters) -> list[str]:
    """Why a variant is rejected (empty when it is kept)."""
    reasons = []
    if registered < filters.min_registered:
        reasons.append(f"registered frames {registered} < {filters.min_registered}")
    if not np.isfinite(reprojection_error):
        reasons.append("no mean reprojection error (nothing registered)")
    elif reprojection_error > filters.max_reprojection_error:
        reasons.append(f"mean reprojection error {reprojection_error:.3f} px > {filters.max_reprojection_error}")
    if scale is None or scale.used == 0 or not np.isfinite(scale.median) or scale.median <= 0:
        reasons.append("no metric scale (no sparse point with a valid disparity)")
    elif scale.iqr > filters.max_scale_iqr_fraction * scale.median:
        reasons.append(f"scale IQR {scale.iqr / scale.median:.1%} of median > {filters.max_scale_iqr_fraction:.0%}")
    return reasons


def stereo_poses(c2w: np.ndarray, scale: float, baseline: float = IRS_BASELINE) -> tuple[np.ndarray, np.ndarray]:
    """Metric left poses (camera centres times ``scale``) and right poses ``cameras.right_camera``
    (``T_L Trans(baseline, 0, 0)``), both [R,4,4] c2w OpenCV, metres."""
    left = np.array(c2w, dtype=np.float64, copy=True)
    left[:, :3, 3] *= scale
    return left, right_camera(left, baseline)


@dataclass
class VariantConfig:
    """Everything a variant run needs besides its folder (picklable, for worker processes)."""

    out: Path
    camera: PinholeCamera = IRS_CAMERA
    focal_baseline: float = IRS_FOCAL_BASELINE
    baseline: float = IRS_BASELINE
    filters: Filters = Filters()
    options: RecoveryOptions = field(default_factory=RecoveryOptions)
    keep_colmap: bool = False


def _poses_json(variant: IrsVariant, recovery: Recovery, scale: ScaleEstimate, cfg: VariantConfig) -> dict:
    left, right = stereo_poses(recovery.c2w, scale.median, cfg.baseline)
    frames = []
    for i, cl, cr in zip(recovery.indices, left, right):
        f = variant.frames[i]
        frames.append({"frame": f.n, "left": f.left.name, "right": f.right.name, "disparity": f.disparity.name,
                       "c2w_left": cl.tolist(), "c2w_right": cr.tolist()})
    return {"variant": variant.name, "source": str(variant.path), "convention": "opencv c2w, metres",
            "width": cfg.camera.width, "height": cfg.camera.height, "K": cfg.camera.K.tolist(),
            "baseline": cfg.baseline, "scale": scale.median, "frames": frames}


def recover_variant(root: Path, folder: Path, cfg: VariantConfig) -> dict[str, Any]:
    """Run one variant end to end and write ``OUT/<variant>/report.json`` (and ``poses.json`` when a metric
    scale exists). Returns the report. Broken inputs and COLMAP failures end up in the report (``kept``
    false with ``reasons``), never as an exception."""
    start = time.perf_counter()
    variant = scan_variant(root, folder)
    out = Path(cfg.out) / variant.name
    report: dict[str, Any] = {"variant": variant.name, "source": str(variant.path), "kept": False, "reasons": [],
                              "thresholds": asdict(cfg.filters)}
    try:
        check_sizes(variant, cfg.camera)
        report.update(frames_found=len(variant.frames) + sum(variant.problems.values()),
                      frames_used=len(variant.frames), frames_left_out=dict(variant.problems))
        if len(variant.frames) < 2:
            report["registered"] = 0
            report["reasons"] = [f"too few usable frames ({len(variant.frames)})"]
        else:
            recovery = recover_poses([f.left for f in variant.frames], cfg.camera, out / "colmap", cfg.options)
            scale = metric_scale(recovery, variant.frames, cfg.focal_baseline) if recovery.registered else None
            err = recovery.mean_reprojection_error
            report.update(registered=recovery.registered, models=recovery.num_models, matching=recovery.matching,
                          points3D=recovery.num_points3D, camera_params=recovery.camera_params,
                          colmap_seconds=recovery.seconds,
                          mean_reprojection_error=err if np.isfinite(err) else None)
            if scale is not None:
                report.update(scale_median=scale.median if scale.used else None,
                              scale_iqr=scale.iqr if scale.used else None,
                              scale_observations=scale.used, invalid_disparity_observations=scale.invalid)
            report["reasons"] = filter_reasons(recovery.registered, err, scale, cfg.filters)
            report["kept"] = not report["reasons"]
            if scale is not None and scale.used:
                atomic_write_json(out / "poses.json", _poses_json(variant, recovery, scale, cfg), indent=None)
    except Exception as exc:  # a broken variant must not stop the dataset: it is reported instead
        report["kept"] = False
        report["reasons"] = [f"error: {type(exc).__name__}: {exc}"]
        report["traceback"] = traceback.format_exc(limit=5)
    finally:
        if not cfg.keep_colmap:
            shutil.rmtree(out / "colmap", ignore_errors=True)
    report["seconds"] = round(time.perf_counter() - start, 3)
    atomic_write_json(out / "report.json", report)
    return report


def _run_one(args: tuple[Path, Path, VariantConfig]) -> dict[str, Any]:
    return recover_variant(*args)


def run_dataset(root: Path, cfg: VariantConfig, workers: int = 1, progress: bool = True) -> list[dict[str, Any]]:
    """Recover every variant under ``root`` into ``cfg.out``, ``workers`` variants at a time (processes;
    COLMAP's threads are shared out between them). Variants whose ``report.json`` exists are skipped (their
    report is reused). Writes ``OUT/summary.json``; returns the reports sorted by variant. ValueError when two
    folders map to the same variant name."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from tqdm import tqdm

    root, out = Path(root), Path(cfg.out)
    cfg.options.matching_for(MIN_REGISTERED_FRAMES)  # bad options fail here, not as a report per variant
    folders = find_variants(root)
    names = Counter(variant_name(root, f) for f in folders)
    clash = sorted(str(f) for f in folders if names[variant_name(root, f)] > 1)
    if clash:
        raise ValueError(f"{root}: these variant folders map to the same output name: {', '.join(clash)}")
    reports: dict[str, dict[str, Any]] = {}
    todo = []
    for folder in folders:
        done = out / variant_name(root, folder) / "report.json"
        if done.is_file():
            reports[done.parent.name] = _read_report(done)
        else:
            todo.append(folder)
    workers = max(1, min(workers, len(todo))) if todo else 1
    if cfg.options.num_threads < 1:
        threads = max(1, (multiprocessing.cpu_count() or 1) // workers)
        cfg = replace(cfg, options=replace(cfg.options, num_threads=threads))
    bar = tqdm(total=len(todo), desc="IRS variants", unit="variant", disable=not progress)
    frames_done = 0
    if workers == 1:
        for r in (recover_variant(root, f, cfg) for f in todo):
            reports[r["variant"]] = r
            frames_done += r.get("frames_used", 0)
            bar.set_postfix(frames=frames_done)
            bar.update()
    else:
        ctx = multiprocessing.get_context("spawn")  # COLMAP runs threads; never fork a process that has them
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=quiet_worker_interrupts) as pool:
            futures = {pool.submit(_run_one, (root, f, cfg)): f for f in todo}
            for fut in as_completed(futures):
                try:
                    r = fut.result()
                except Exception as exc:  # the worker process died: report it, write no report.json (retry)
                    name = variant_name(root, futures[fut])
                    r = {"variant": name, "kept": False, "reasons": [f"worker failed: {type(exc).__name__}: {exc}"]}
                reports[r["variant"]] = r
                frames_done += r.get("frames_used", 0)
                bar.set_postfix(frames=frames_done)
                bar.update()
    bar.close()
    ordered = [reports[k] for k in sorted(reports)]
    atomic_write_json(out / "summary.json", {"dataset": str(root), "variants": len(ordered),
                                             "kept": sum(r["kept"] for r in ordered), "reports": ordered})
    return ordered


def _read_report(path: Path) -> dict[str, Any]:
    import json

    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        return {"variant": Path(path).parent.name, "kept": False, "reasons": [f"unreadable report: {exc}"]}


def summary_table(reports: list[dict[str, Any]]) -> str:
    """A fixed-width table: one row per variant (frames used, registered, reprojection error in px, scale
    in metres per unit, IQR as % of the median, seconds, s/100 frames, kept or why not) and a total row."""

    def num(value: Any, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    rows = [("variant", "frames", "reg", "reproj", "scale", "IQR%", "s", "s/100f", "kept / why not")]
    for r in reports:
        frames, secs = r.get("frames_used"), r.get("seconds")
        med, iqr = r.get("scale_median"), r.get("scale_iqr")
        rows.append((r["variant"], num(frames, "d"), num(r.get("registered"), "d"),
                     num(r.get("mean_reprojection_error"), ".3f"), num(med, ".4g"),
                     num(100 * iqr / med if med and iqr is not None else None, ".1f"), num(secs, ".1f"),
                     num(100 * secs / frames if secs and frames else None, ".1f"),
                     "kept" if r["kept"] else "; ".join(r.get("reasons", []))))
    frames = sum(r.get("frames_used") or 0 for r in reports)
    secs = sum(r.get("seconds") or 0 for r in reports)
    rows.append((f"total {len(reports)}", str(frames), str(sum(r.get("registered") or 0 for r in reports)), "", "",
                 "", f"{secs:.1f}", num(100 * secs / frames if frames else None, ".1f"),
                 f"{sum(r['kept'] for r in reports)} kept"))
    return format_table(rows, align="l" * len(rows[0]), rule=True, free_last=True)
