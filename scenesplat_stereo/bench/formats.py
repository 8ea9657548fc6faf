"""``scenesplat-stereo bench formats``: the scene file formats, read and written (docs/formats.md's tables).

1. Readers: every real capture under ``--captures`` (PlayCanvas ``.sog``, antimatter15 ``.splat``; default
   ../shared/data/captures) and every streamed scene under ``--streamed`` (folders holding ``lod-meta.json``,
   read at level 0): Gaussians, SH degree, bytes on disk and per Gaussian, read time (median of ``--repeats``).
2. Writers: each ``--scene`` (default: the guitar teacher's float ``.ply``, SH 0, and the skull capture, SH 3,
   as read) written in every format of ``scene_files.FORMATS`` and read back: size (and against ``.ply``),
   write and read time, and the error of what is read back against the scene written: position (world units),
   rotation (largest |component| difference of the unit quaternions, up to sign), log-scale, opacity, SH DC
   (f_dc) and the higher SH coefficients, each as the largest and the root mean square. The compressed
   ``.ply`` and SOG writers reorder the Gaussians along a Morton curve; they are compared in that order.
   With node and splat-transform installed (``cd scripts/checks/viewer && npm ci``), SH-0 scenes also get a row for
   splat-transform 3.7.0's own SOG writer (``splat-transform -w SCENE.ply OUT.sog``; its SH palette needs a GPU).
Prints markdown tables and the machine; ``--out`` also writes them to a file.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import whole_number
from scenesplat_stereo.scene.compressed_ply import morton_order
from scenesplat_stereo.scene.gaussians import GaussianScene
from scenesplat_stereo.scene.scene_files import FORMATS, load_scene, save_scene, scene_kind

OWNER = "scenesplat-stereo bench formats"  # recorded beside --out: a rerun may replace its own report
SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
SPLAT_TRANSFORM = (Path(__file__).resolve().parents[2] / "scripts" / "checks" / "viewer" / "node_modules"
                   / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--captures", type=Path, default=SHARED / "captures", help="folder of capture folders "
                   "(default ../shared/data/captures beside the checkout)")
    p.add_argument("--streamed", type=Path, default=Path(os.environ.get("STREAMED_SCENES", SHARED / "streamed")),
                   help="folder of streamed SOG folders (default $STREAMED_SCENES, else ../shared/data/streamed beside the "
                   "checkout; skipped when absent)")
    p.add_argument("--scene", type=Path, action="append", default=None,
                   help="a scene to write in every format (repeatable; default the guitar .ply and skull.sog)")
    p.add_argument("--repeats", type=whole_number("--repeats"), default=3, help="reads timed per file (median)")
    p.add_argument("--out", type=Path, default=None, help="also write the tables to this markdown file (a report "
                   "of an earlier run of this bench is replaced, any other file refused)")


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, value = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        value = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), value


def reader_table(captures: list[Path], repeats: int) -> str:
    rows = ["| capture | format | Gaussians | SH | MB | bytes / Gaussian | read (s) |",
            "|---|---|---:|---:|---:|---:|---:|"]
    for path in captures:
        files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
        size = sum(p.stat().st_size for p in files)
        seconds, scene = _median_time(lambda: load_scene(path), repeats)
        kind = scene_kind(path)
        kind = {"lod": "streamed SOG, level 0", "sog": "SOG", "splat": ".splat"}.get(kind, kind)
        rows.append(f"| {path.parent.name if path.is_file() else path.name} | {kind} | {len(scene):,} | "
                    f"{scene.sh_degree} | {size / 1e6:.2f} | {size / len(scene):.1f} | {seconds:.2f} |")
    return "\n".join(rows)


def scene_errors(ref: GaussianScene, back: GaussianScene) -> dict[str, tuple[float, float]]:
    """(largest, RMS) of what was read back against what was written, per field (module docstring)."""
    q_ref = ref.quats / np.linalg.norm(ref.quats, axis=1, keepdims=True)
    diffs = {"position": back.means - ref.means,
             "rotation": np.minimum(np.abs(back.quats - q_ref).max(1), np.abs(back.quats + q_ref).max(1)),
             "log-scale": np.log(back.scales.astype(np.float64)) - np.log(ref.scales.astype(np.float64)),
             "opacity": back.opacities - ref.opacities, "f_dc": back.sh[:, 0] - ref.sh[:, 0],
             "higher SH": back.sh[:, 1:] - ref.sh[:, 1:]}
    return {k: (float(np.abs(d).max()), float(np.sqrt((d.astype(np.float64) ** 2).mean()))) if d.size else (0.0, 0.0)
            for k, d in diffs.items()}


def writer_table(scenes: list[Path], repeats: int) -> str:
    fields = ("position", "rotation", "log-scale", "opacity", "f_dc", "higher SH")
    rows = ["| scene | format | bytes / Gaussian | vs .ply | write (s) | read (s) | "
            + " | ".join(f"{f} max / RMS" for f in fields) + " |",
            "|---|---|---:|---:|---:|---:|" + "---|" * len(fields)]
    for path in scenes:
        scene = load_scene(path)
        name = f"{path.name} ({len(scene):,}, SH {scene.sh_degree})"
        sizes = {}
        theirs = SPLAT_TRANSFORM.is_file() and shutil.which("node") and scene.sh_degree == 0
        with tempfile.TemporaryDirectory(prefix="bench-formats-") as tmp:
            for fmt, spec in [*FORMATS.items(), *([("sog (splat-transform)", FORMATS["sog"])] if theirs else [])]:
                out = Path(tmp) / f"{fmt.split()[0]}-{len(sizes)}{spec.suffix}"
                t0 = time.perf_counter()
                if fmt in FORMATS:
                    save_scene(scene, out, fmt, durable=False)
                else:
                    ply = save_scene(scene, Path(tmp) / "input.ply", "ply", durable=False)
                    subprocess.run(["node", str(SPLAT_TRANSFORM), "-w", str(ply), str(out)], check=True,
                                   capture_output=True)
                write_s = time.perf_counter() - t0
                read_s, back = _median_time(lambda: load_scene(out), repeats)
                sizes[fmt] = out.stat().st_size
                ref = scene.subset(morton_order(scene.means)) if fmt.startswith(("compressed-ply", "sog")) else scene
                err = scene_errors(ref, back)
                rows.append(f"| {name} | {fmt} | {sizes[fmt] / len(scene):.1f} | {sizes['ply'] / sizes[fmt]:.1f}x | "
                            f"{write_s:.2f} | {read_s:.2f} | "
                            + " | ".join(f"{err[f][0]:.3g} / {err[f][1]:.3g}" for f in fields) + " |")
    return "\n".join(rows)


def run(args: argparse.Namespace) -> int:
    out = OwnedFile(args.out, "--out", OWNER)  # before any work
    captures = sorted(p for p in args.captures.glob("*/*") if p.suffix in (".sog", ".splat")) \
        if args.captures.is_dir() else []
    captures += sorted(p for p in args.streamed.glob("*") if (p / "lod-meta.json").is_file()) \
        if args.streamed.is_dir() else []
    scenes = args.scene or [p for p in (SHARED / "teachers" / "playcanvas-guitar" / "point_cloud.ply",
                                        args.captures / "skull" / "skull.sog") if p.is_file()]
    if not captures and not scenes:
        raise ValueError(f"--captures {args.captures}: no captures, and no --scene to write")
    machine = f"{platform.node()}: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs (shared)"
    text = "\n\n".join([f"Machine: {machine}; reads are medians of {args.repeats}.",
                        "Readers (real captures):", reader_table(captures, args.repeats),
                        "Writers (each format written and read back):", writer_table(scenes, args.repeats)])
    print(text)
    out.write(text + "\n")
    return 0
