"""``scenesplat-stereo build``: teacher scenes -> SceneSplat-Stereo shards (SPEC sections 3-5).

Orchestration only: teachers (discovery, PSNR filter) -> protocol (splits, sample plans) -> the Warp
rasteriser (all cameras of several pairs per call) -> encoder threads or processes (and nvJPEG) -> shards.
The settings and flags live in ``build_settings``.

Work is cut into shards per teacher: the teachers of a split, in sorted scene-id order, each take
ceil(samples / --samples-per-shard) consecutive shard numbers, so ``OUT/<split>/shard-<NNNNNN>.tar`` is
fixed by the inputs alone and any worker (a local loop or a Ray task per teacher) can write any
teacher's shards. A rerun keeps every shard that is finished (its done marker lists exactly the planned
keys and its size matches) and redoes the rest; a teacher whose shards are all finished is not even
loaded. Same inputs, same bytes: shards, markers, ``index.json`` and ``stats.json`` hold no timestamps.
Ctrl-C ends a build with one line saying how many shards are finished (``Interrupted``, exit 130).

A teacher that cannot be rendered (unreadable ``.ply``, NaNs in it, a render error) is reported in the
summary and skipped; the others go on, and the teacher's unfinished shard is removed.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
import warnings
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenesplat_stereo.build.protocol import (MASK_ALPHA_THRESHOLD, TEST_PAIRS_PER_SCENE, VAL_SCENES, SamplePlan,
                                              filter_teachers, plan_scene, split_scenes)
from scenesplat_stereo.build.render_pairs import start_render, stream_samples
from scenesplat_stereo.build.settings import SPLITS_OF_MODE, BuildSettings, add_arguments, settings_from_args
from scenesplat_stereo.common.commandline import Interrupted, NotAvailable
from scenesplat_stereo.common.files import read_json
from scenesplat_stereo.common.ownership import check_apart, check_replaceable
from scenesplat_stereo.common.text import format_table
from scenesplat_stereo.scene.cameras import baseline_doubt
from scenesplat_stereo.scene.scene_files import load_scene
from scenesplat_stereo.scene.teachers import (Discovery, Rejection, Teacher, discover_teachers, resolve_trajectory,
                                              summary_table)
from scenesplat_stereo.shards import webdataset as shards
from scenesplat_stereo.shards.benchmark_file import Benchmark, write_benchmark
from scenesplat_stereo.shards.encode_pool import SampleEncoder
from scenesplat_stereo.shards.nvjpeg import NvJpegEncoder

__all__ = ["BuildSettings", "BuildReport", "add_arguments", "build", "run", "settings_from_args", "summary"]

BUILD_JSON = "build.json"
log = logging.getLogger(__name__)
OWNER = "scenesplat-stereo build"  # a folder holding BUILD_JSON is a build's (it resumes); any other must be empty
EXIT_TEACHER_FAILED = 3  # exit status when some teachers failed at build time (the rest is complete)


@dataclass
class TeacherJob:
    """One teacher's work: its split and the shards still to write, each (number, planned keys)."""

    teacher: Teacher
    split: str
    chunks: list[tuple[int, list[str]]]

    @property
    def pairs(self) -> int:
        return sum(len(keys) for _, keys in self.chunks)


@dataclass
class TeacherResult:
    scene_id: str
    subset: str
    split: str
    pairs: int = 0
    renders: int = 0
    shards: int = 0
    render_s: float = 0.0
    encode_s: float = 0.0
    write_s: float = 0.0
    error: str | None = None
    path: str = ""
    started: float = 0.0  # when its task began and ended (time.time(), s: one host's clock; not in any file)
    finished: float = 0.0
    worker: str = ""  # host:pid of the process that built it (not in any file)


@dataclass
class BuildReport:
    """What a build did: teachers (found, dropped with reasons), work done and skipped, timings (s)."""

    discovery: Discovery
    dropped: list[Rejection] = field(default_factory=list)
    planned: dict[str, dict[str, int]] = field(default_factory=dict)  # split -> teachers/pairs/shards
    results: list[TeacherResult] = field(default_factory=list)
    skipped_shards: int = 0
    removed_stale: int = 0
    wall_s: float = 0.0

    @property
    def failed(self) -> list[TeacherResult]:
        return [r for r in self.results if r.error]


def plan_teacher(teacher: Teacher, split: str, settings: BuildSettings) -> list[SamplePlan]:
    """The samples of one teacher (protocol.plan_scene), capped at ``max_frames`` evenly spaced ones."""
    plans = plan_scene(teacher, split, settings.baseline, settings.rho, settings.targets, settings.resolution)
    cap = settings.max_frames
    if cap is not None and len(plans) > cap:
        plans = [plans[int(i)] for i in np.unique(np.linspace(0, len(plans) - 1, cap).round())]
    return plans


def _planned_keys(teacher: Teacher, split: str, settings: BuildSettings) -> list[str]:
    """Sample keys without loading the .ply (orbit teachers: any centre gives the same frames)."""
    if teacher.c2w is None:
        teacher = resolve_trajectory(teacher, np.zeros((1, 3)))
    return [p.key for p in plan_teacher(teacher, split, settings)]


def build_teacher(job: TeacherJob, settings: BuildSettings, on_pairs=None) -> TeacherResult:
    """Render, encode and write the missing shards of one teacher. Never raises for a bad teacher: the
    error is returned in the result, and no unfinished shard is left behind."""
    t = job.teacher
    result = TeacherResult(t.scene_id, t.subset, job.split, path=str(t.ply_path), started=time.time(),
                           worker=f"{socket.gethostname()}:{os.getpid()}")
    sink = shards.PlannedShards(settings.out, job.split, job.chunks)
    encoder = jpeg = None
    try:
        scene = load_scene(t.ply_path, strict=True)
        teacher = resolve_trajectory(t, scene.means) if t.c2w is None else t
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the driver already reported the planning warnings
            by_key = {p.key: p for p in plan_teacher(teacher, job.split, settings)}
        todo = [by_key[k] for _, keys in job.chunks for k in keys]
        gaussians = scene.to_torch(settings.device)
        jpeg = None if settings.jpeg_encoder == "cpu" else NvJpegEncoder(settings.device, settings.jpeg_quality)
        batches = [todo[s:s + settings.batch_pairs] for s in range(0, len(todo), settings.batch_pairs)]
        rendered = stream_samples(batches, lambda b: start_render(
            gaussians, scene.sh_degree, b, settings.device, settings.with_depth, settings.effects, jpeg=jpeg))
        encoder = SampleEncoder(sink, settings.workers, settings.jpeg_quality, mode=settings.encoder_mode)
        with encoder:  # its threads are joined when this block ends, whatever happens in it
            for batch in batches:
                t0 = time.perf_counter()
                samples = next(rendered)
                result.render_s += time.perf_counter() - t0
                renders = sum(2 + len(p.target_ids) for p in batch)
                result.renders += renders
                for sample in samples:
                    encoder.submit(sample)
                if on_pairs is not None:
                    on_pairs(len(batch), renders)
    except Exception as e:  # noqa: BLE001  (one bad teacher must not stop the others; reported)
        sink.discard()
        result.error = f"{type(e).__name__}: {e}"
    if jpeg is not None:
        jpeg.close()
    if encoder is not None:
        result.encode_s, result.write_s = encoder.encode_s, encoder.sink_s
    result.shards, result.pairs = sink.done, sink.pairs
    result.finished = time.time()
    return result


def _run_local(jobs: list[TeacherJob], settings: BuildSettings, bar: tqdm) -> list[TeacherResult]:
    results = []
    for job in jobs:
        bar.set_description(job.teacher.scene_id[:24])
        results.append(build_teacher(job, settings, on_pairs=lambda n, r: _advance(bar, n, r)))
    return results


def _run_ray(jobs: list[TeacherJob], settings: BuildSettings, bar: tqdm) -> list[TeacherResult]:
    try:
        import ray
    except ImportError:
        raise NotAvailable("--backend ray needs Ray: pip install 'stereogaussians[ray]'") from None
    if not ray.is_initialized():
        ray.init(address=settings.ray_address)
    # max_calls=0: a worker process builds teacher after teacher. Ray's default for a task that asks for a GPU
    # is one call a process, and a fresh process pays Python, torch, Warp's kernels, CUDA and nvJPEG again for
    # every teacher (seconds each)
    task = ray.remote(num_cpus=1, num_gpus=_ray_gpus(settings), max_calls=0)(build_teacher)
    if settings.encoder_mode == "auto":  # Ray's workers encode in threads: spawning from them is untested
        settings = replace(settings, encoder_mode="threads")
    pending = {task.remote(job, settings): job for job in jobs}
    results = []
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        job = pending.pop(done[0])
        try:
            results.append(ray.get(done[0]))
        except Exception as e:  # noqa: BLE001  (a crashed task is reported like a bad teacher)
            results.append(TeacherResult(job.teacher.scene_id, job.teacher.subset, job.split,
                                         error=f"Ray task failed: {e}", path=str(job.teacher.ply_path)))
        bar.set_description(job.teacher.scene_id[:24])
        _advance(bar, job.pairs, results[-1].renders)
    order = {(j.split, j.teacher.scene_id): i for i, j in enumerate(jobs)}
    return sorted(results, key=lambda r: order[(r.split, r.scene_id)])


def _ray_gpus(settings: BuildSettings) -> int:
    """GPUs a teacher's Ray task asks for: one on CUDA (Ray sets its CUDA_VISIBLE_DEVICES), none on the CPU."""
    return 1 if str(settings.device).startswith("cuda") else 0


def _advance(bar: tqdm, pairs: int, renders: int) -> None:
    """Advance the bar by ``pairs`` (its rate is pairs/s) and show renders/s beside it."""
    bar.renders = getattr(bar, "renders", 0) + renders
    bar.update(pairs)
    elapsed = bar.format_dict.get("elapsed") or 0.0
    if elapsed > 0:
        bar.set_postfix_str(f"{bar.renders / elapsed:.1f} renders/s", refresh=False)


def _val_counts(settings: BuildSettings, subsets: set[str]) -> dict[str, int]:
    if settings.val_scenes is None:
        return {s: VAL_SCENES.get(s, 0) for s in subsets}
    if isinstance(settings.val_scenes, int):
        return {s: settings.val_scenes for s in subsets}
    return dict(settings.val_scenes)


def _check_fingerprint(settings: BuildSettings) -> dict:
    """Refuse to mix outputs of different settings in one OUT (reads only); returns ``build.json`` with
    this build's settings recorded, for ``_record_fingerprint`` once everything else is checked."""
    path = Path(settings.out) / BUILD_JSON
    try:
        doc = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{path}: unreadable ({e}); delete it (and OUT) to rebuild") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object; delete it (and OUT) to rebuild")
    old, new = doc.get(settings.split_mode), settings.fingerprint()
    if old is not None and old != new:
        diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
        raise ValueError(f"{path}: OUT was built ({settings.split_mode}) with other settings ({', '.join(diff)} "
                         "differ); use a new --out, or delete OUT to rebuild")
    return doc | {settings.split_mode: new}


def _check_out(out: Path) -> None:
    """``--out`` must be a folder we can write in (created if missing); checked before anything is written
    or removed."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    if not out.exists():
        parent = next((p for p in out.absolute().parents if p.exists()), None)
        if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise ValueError(f"--out {out}: cannot create it ({parent} is not a writable folder)")
    elif not os.access(out, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out}: not writable")


def plan_build(settings: BuildSettings) -> tuple[BuildReport, list[TeacherJob], dict[str, set[int]]]:
    """Discovery, filter, splits and the shard layout, reading only: returns the report, the jobs (finished
    shards are left out) and, per split, the planned shard numbers (``remove_stale`` removes the others).
    Every refusal (no teacher kept, too few scenes for the validation split, a sample plan that cannot be
    made) is raised here, before the build writes or removes anything."""
    discovery = discover_teachers(settings.teachers, settings.orbit)
    kept, dropped = filter_teachers(discovery.teachers, settings.min_psnr)
    report = BuildReport(discovery, dropped)
    if settings.split_mode == "test":
        split_of = {t.scene_id: "test" for t in kept}
    else:
        by_subset: dict[str, list[str]] = defaultdict(list)
        for t in kept:
            by_subset[t.subset].append(t.scene_id)
        try:
            split_of = split_scenes(by_subset, _val_counts(settings, set(by_subset)))
        except ValueError as e:
            raise ValueError(f"{e} (set --val-scenes)") from None
    if not kept:
        raise ValueError(f"--teachers {settings.teachers}: no teacher to build from ({len(discovery.rejected)} "
                         f"rejected, {len(dropped)} dropped by --min-psnr)\n" + summary_table(discovery, dropped))
    jobs: list[TeacherJob] = []
    layout: dict[str, set[int]] = {}
    for split in SPLITS_OF_MODE[settings.split_mode]:
        number, planned, teachers, pairs = 0, set(), 0, 0
        for t in sorted((t for t in kept if split_of[t.scene_id] == split), key=lambda t: t.scene_id):
            try:
                keys = _planned_keys(t, split, settings)
            except ValueError as e:
                raise ValueError(f"{t.ply_path.parent}: cannot plan its {split} samples: {e}") from None
            chunks = [(number + i, keys[s:s + settings.samples_per_shard])
                      for i, s in enumerate(range(0, len(keys), settings.samples_per_shard))]
            number += len(chunks)
            planned.update(n for n, _ in chunks)
            teachers, pairs = teachers + 1, pairs + len(keys)
            todo = []
            for n, chunk_keys in chunks:
                info = shards.read_done(settings.out, split, n)
                if info is not None and info["keys"] == chunk_keys:
                    report.skipped_shards += 1
                else:
                    todo.append((n, chunk_keys))
            if todo:
                jobs.append(TeacherJob(t, split, todo))
        layout[split] = planned
        report.planned[split] = {"teachers": teachers, "pairs": pairs, "shards": number}
    return report, jobs, layout


def remove_stale(settings: BuildSettings, report: BuildReport, layout: dict[str, set[int]]) -> None:
    """Remove the shards of an earlier layout that this build does not plan (counted in the report)."""
    for split, planned in layout.items():
        stale = shards.remove_unplanned(settings.out, split, planned)
        if stale:
            warnings.warn(f"{Path(settings.out) / split}: removed {stale} shards that this build does not plan "
                          "(an earlier layout)", stacklevel=2)
        report.removed_stale += stale


def build(settings: BuildSettings) -> BuildReport:
    """Run a build (see the module docstring) and return its report; prints nothing but the progress bar."""
    t_start = time.perf_counter()
    # Everything is checked (settings at construction, OUT, earlier settings, teachers, plans) before the
    # first write: a refused command leaves OUT as it was, so the corrected command is not refused.
    _check_out(settings.out)
    check_replaceable(settings.out, "--out", OWNER, marker=BUILD_JSON)
    check_apart(settings.out, "--out", {"--teachers": settings.teachers}, replaced=True)
    recorded = _check_fingerprint(settings)
    report, jobs, layout = plan_build(settings)
    Path(settings.out).mkdir(parents=True, exist_ok=True)
    shards.atomic_write_bytes(Path(settings.out) / BUILD_JSON,
                              (json.dumps(recorded, indent=1, sort_keys=True) + "\n").encode())
    remove_stale(settings, report, layout)
    total = sum(j.pairs for j in jobs)
    try:
        with tqdm(total=total, unit="pair", disable=not settings.progress, dynamic_ncols=True) as bar:
            run = _run_ray if settings.backend == "ray" else _run_local
            report.results = run(jobs, settings, bar)
    except KeyboardInterrupt:
        done = sum(len(shards.finished_shards(settings.out, split)) for split in layout)
        planned = sum(plan["shards"] for plan in report.planned.values())
        raise Interrupted(f"{done} of {planned} shards of {settings.out} are finished and kept (each whole); rerun "
                          f"the same command to resume") from None
    for split in SPLITS_OF_MODE[settings.split_mode]:
        shards.write_index(settings.out, split)
    _write_stats(settings, report)
    if settings.split_mode == "test":
        write_benchmark(settings.out, rendered_benchmark(settings))
    report.wall_s = time.perf_counter() - t_start
    return report


def rendered_benchmark(settings: BuildSettings) -> Benchmark:
    """How a rendered test set is measured (``OUT/benchmark.json``): over the valid masks, as the paper
    measures ReplicaGS."""
    pairs = TEST_PAIRS_PER_SCENE if settings.max_frames is None else min(TEST_PAIRS_PER_SCENE, settings.max_frames)
    b = "tier" if settings.baseline is None else f"{settings.baseline:g} m"
    rho = "tier" if settings.rho is None else f"{settings.rho:g} m"
    return Benchmark(masked=True, source="rendered", protocol=(
        f"rendered from 3DGS teachers: {pairs} evenly spaced pairs per scene, {settings.targets} targets, B {b}, "
        f"rho {rho}; metrics over rendered alpha >= {MASK_ALPHA_THRESHOLD}"))



def _write_stats(settings: BuildSettings, report: BuildReport) -> None:
    path = Path(settings.out) / shards.STATS_NAME
    doc = read_json(path) if path.is_file() else {}
    old = doc.get("teachers", {}) if isinstance(doc, dict) else {}
    drops = report.discovery.rejected + report.dropped + _failed_as_rejections(report)
    old[settings.split_mode] = {
        "found": len(report.discovery.teachers) + len(report.discovery.rejected),
        "kept": len(report.discovery.teachers) - len(report.dropped) - len(report.failed),
        "dropped": [{"scene": d.scene_id, "subset": d.subset, "reason": d.reason} for d in drops],
    }
    shards.write_stats(settings.out, shards.collect_stats(settings.out) | {"teachers": old})


def _failed_as_rejections(report: BuildReport) -> list[Rejection]:
    return [Rejection(r.scene_id, Path(r.path), f"build failed: {r.error}", r.subset) for r in report.failed]


def summary(report: BuildReport) -> str:
    """The end-of-build table: teachers found/kept/dropped (with reasons), per split the planned
    teachers, pairs and shards and this run's work, and the time split."""
    lines = ["teachers:", summary_table(report.discovery, report.dropped + _failed_as_rejections(report)), ""]
    rows = [("split", "teachers", "pairs", "shards", "rendered pairs", "renders", "shards written")]
    for split, plan in report.planned.items():
        done = [r for r in report.results if r.split == split]
        rows.append((split, str(plan["teachers"]), str(plan["pairs"]), str(plan["shards"]),
                     str(sum(r.pairs for r in done)), str(sum(r.renders for r in done)),
                     str(sum(r.shards for r in done))))
    lines.append(format_table(rows))
    pairs = sum(r.pairs for r in report.results)
    renders = sum(r.renders for r in report.results)
    render_s = sum(r.render_s for r in report.results)
    rate = f"{pairs / report.wall_s:.2f} pairs/s, {renders / report.wall_s:.1f} renders/s" if report.wall_s else "-"
    ran = [r for r in report.results if r.finished > 0]
    window = max(r.finished for r in ran) - min(r.started for r in ran) if ran else 0.0
    lines += [
        "",
        f"kept from an earlier run: {report.skipped_shards} shards; removed stale: {report.removed_stale}",
        f"time: render {render_s:.1f} s, encode {sum(r.encode_s for r in report.results):.1f} worker-s, "
        f"write {sum(r.write_s for r in report.results):.1f} s, wall {report.wall_s:.1f} s ({rate})"
        + (f"; first teacher's start to last one's end {window:.1f} s ({pairs / window:.2f} pairs/s)"
           if window > 0 else "")
        + (f"; {len(ran)} teachers in {len({r.worker for r in ran})} processes" if ran else ""),
    ]
    return "\n".join(lines)


def run(args) -> int:
    """CLI entry: build, print the summary; exit 0, or ``EXIT_TEACHER_FAILED`` if some teacher failed. A refused
    input raises (nothing is written then); ``commandline.run_command`` makes it one line and exit 2."""
    settings = settings_from_args(args)
    if settings.baseline is not None:
        hint = "--baseline is in the teachers' world units, metres for metric scenes (10 cm is --baseline 0.1)"
        doubt = baseline_doubt(settings.baseline, f"--baseline {settings.baseline:g}", hint, hint)
        if doubt:
            log.warning(doubt)
    report = build(settings)
    print(summary(report))
    return EXIT_TEACHER_FAILED if report.failed else 0
