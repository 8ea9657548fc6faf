"""``scenesplat-stereo bench scenes``: every scene writer's time and file size at N Gaussians (issue 35).

The scene is synthetic and shaped like a prediction (``sgmodel predict`` at 320x256 makes 202,752
Gaussians, ``--gaussians``): layers of a 320x256 pixel grid back-projected (f = 288 px) onto smooth depth
surfaces 2-3 m away, one Gaussian a pixel with the pixel's footprint as its scale, smooth colours,
quaternions near the identity, opacities uniform in [0.05, 1]; for SH degree d > 0 the higher coefficients
are drawn from N(0, 0.02^2) (``sgmodel bench predict`` adds the same to a fresh model's scene). gzip's time
depends on the bytes, so a real prediction's ``.spz`` may take somewhat more or less.

Each writer of ``scene_files.FORMATS`` writes the scene as ``sgmodel predict`` does (atomically, without
fsync), then the ``.ply`` with fsync (what the fsync costs), ``--warmup`` untimed and ``--repeats`` timed
times into a temporary folder (``--folder``: on that disk); the table gives the median and the fastest run,
and the median CPU time of the process (all threads: what the write costs the machine).
A last row per degree times the ``.spz``'s deflate alone (``zlib`` level 6 of the uncompressed stream, one
thread): the serial part of a byte-identical ``.spz`` writer, which no threading removes.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import markdown_table
from scenesplat_stereo.scene import row_tasks
from scenesplat_stereo.scene.gaussians import GaussianScene, save_ply
from scenesplat_stereo.scene.ply import SH_C0
from scenesplat_stereo.scene.scene_files import FORMATS, save_scene
from scenesplat_stereo.scene.spz import GZIP_LEVEL, encode_spz

OWNER = "scenesplat-stereo bench scenes"  # recorded beside --out: a rerun may replace its own report
#: The Gaussians ``sgmodel predict`` makes from a 320x256 pair (two layers on the padded canvas).
PREDICTION_GAUSSIANS = 202_752
#: Columns of ``writer_rows``.
COLUMNS = ["writer", "SH degree", "Gaussians", "median ms", "min ms", "CPU ms", "MB", "x smaller than .ply"]


def synthetic_scene(n: int = PREDICTION_GAUSSIANS, sh_degree: int = 0, seed: int = 0) -> GaussianScene:
    """A prediction-shaped scene of ``n`` Gaussians (module docstring), float32, metres."""
    rng = np.random.default_rng(seed)
    w, h, f = 320, 256, 288.0
    v, u = (a.ravel() for a in np.mgrid[0:h, 0:w].astype(np.float64))
    layer = np.arange(n) // (w * h)
    u, v = u[np.arange(n) % (w * h)], v[np.arange(n) % (w * h)]
    z = 2.0 + 0.4 * np.sin(u / 37.0) * np.cos(v / 53.0) + v / 400.0 + 0.25 * layer
    means = np.stack([(u - w / 2) / f * z, (v - h / 2) / f * z, z], 1)
    scales = (z / f)[:, None] * rng.uniform(0.8, 1.6, (n, 3))
    quats = np.array([1.0, 0.0, 0.0, 0.0]) + rng.normal(0, 0.1, (n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    colour = 0.5 + 0.4 * np.stack([np.sin(u / 23.0 + c) * np.cos(v / 29.0 - c) for c in range(3)], 1)
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3))
    sh[:, 0] = (colour - 0.5) / SH_C0
    sh[:, 1:] = rng.normal(0, 0.02, sh[:, 1:].shape)
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return GaussianScene(f32(means), f32(quats), f32(scales), f32(rng.uniform(0.05, 1.0, n)), f32(sh), sh_degree)


def _times(run: Callable[[], object], warmup: int, repeats: int) -> list[str]:
    """[median ms, min ms, median CPU ms] of ``repeats`` runs after ``warmup``: wall time, and the process's CPU
    time (all threads; less sensitive to other processes on a shared machine than the wall time)."""
    wall, cpu = [], []
    for i in range(warmup + repeats):
        t, c = time.perf_counter(), time.process_time()
        run()
        if i >= warmup:
            wall.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
    return [f"{1e3 * statistics.median(wall):.1f}", f"{1e3 * min(wall):.1f}", f"{1e3 * statistics.median(cpu):.1f}"]


def writer_rows(scene: GaussianScene, folder: Path, warmup: int, repeats: int, label: str | None = None,
                deflate: bool = True) -> list[list[str]]:
    """Rows of ``COLUMNS`` for ``scene`` written by every writer into ``folder`` (module docstring); ``label``
    replaces the SH degree column's text; ``deflate`` adds the .spz deflate row."""
    degree = label or str(scene.sh_degree)
    writers: list[tuple[str, Callable[[Path], object], str]] = [
        (name, lambda p, f=name: save_scene(scene, p, f, durable=False), fmt.suffix) for name, fmt in FORMATS.items()]
    writers.append(("ply, fsync'd", lambda p: save_ply(scene, p, durable=True), ".ply"))
    rows, sizes = [], {}
    for name, write, suffix in writers:
        path = folder / f"bench{suffix}"
        times = _times(lambda: write(path), warmup, repeats)
        sizes[name] = path.stat().st_size
        rows.append([name, degree, f"{len(scene):,}", *times, f"{sizes[name] / 1e6:.2f}",
                     f"{sizes['ply'] / sizes[name]:.1f}"])
    if deflate and "spz" in sizes:
        raw = encode_spz(scene)
        times = _times(lambda: zlib.compress(raw, GZIP_LEVEL), warmup, repeats)
        rows.append([f"spz: its deflate alone (zlib {GZIP_LEVEL}, one thread)", degree, f"{len(scene):,}", *times,
                     "", ""])
    return rows


def machine() -> str:
    """'<CPU model>, <n> of <m> CPUs usable, <k> row-task threads' of this host (Linux)."""
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {len(os.sched_getaffinity(0))} of {os.cpu_count()} CPUs usable, {row_tasks.workers()} " \
           f"row-task threads"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--gaussians", type=int, default=PREDICTION_GAUSSIANS,
                   help=f"Gaussians in the scene (default {PREDICTION_GAUSSIANS:,}: a 320x256 prediction's)")
    p.add_argument("--sh-degrees", type=int, nargs="+", default=[0, 2], choices=range(4),
                   help="SH degrees to time (default 0 2: naive-GS's and a trained model's)")
    p.add_argument("--warmup", type=int, default=2, help="untimed writes first (default 2)")
    p.add_argument("--repeats", type=int, default=11, help="timed writes (default 11)")
    p.add_argument("--folder", type=Path, help="write the files in a temporary folder inside this one "
                   "(default: the system's temporary folder)")
    p.add_argument("--out", type=Path, help="also write the markdown here (a report of an earlier run of this bench "
                   "is replaced, any other file refused)")


def run(args: argparse.Namespace) -> int:
    if args.gaussians < 1 or args.warmup < 0 or args.repeats < 1:
        raise ValueError(f"--gaussians and --repeats must be at least 1 and --warmup at least 0, got "
                         f"{args.gaussians}, {args.repeats} and {args.warmup}")
    out = OwnedFile(args.out, "--out", OWNER)  # before any work
    rows = []
    with tempfile.TemporaryDirectory(dir=args.folder) as tmp:
        for degree in args.sh_degrees:
            rows += writer_rows(synthetic_scene(args.gaussians, degree), Path(tmp), args.warmup, args.repeats)
    load = ", load average {:.1f} {:.1f} {:.1f}".format(*os.getloadavg()) if hasattr(os, "getloadavg") else ""
    text = (f"Scene writers on {machine()}{load}: {args.gaussians:,} prediction-shaped Gaussians, each write "
            f"atomic without fsync unless said; median and fastest of {args.repeats} after {args.warmup}, and "
            f"the median CPU time (all threads).\n\n"
            f"{markdown_table(COLUMNS, rows)}\n")
    print(text)
    out.write(text)
    return 0
