"""Where the SOG writer's time goes (issue 35): a timeline of one ``sog.encode_sog`` of the bench scene, each
stage's start and end on each thread, so that what holds up the whole (the path from the first stage to the
zip) can be read off on the machine measured.

    python scripts/profile/sog_timeline.py [--gaussians 202752] [--sh-degree 0] [--repeats 5] [--out FILE]

The scene is ``bench scenes``' prediction-shaped one. The stages are the writer's own functions, wrapped for the run
(the texels' three stages ``placed``, ``scale_texels`` and ``colour_texels``, on the GPU where there is one; the
codebooks, the nearest-entry labels, the SH palette's k-means, the quaternion bytes, the Morton order, every WebP
encode) and every task of the shared pool of ``row_tasks`` (``_encoded`` there is an encode and its CRC, timed
again inside).
``--repeats`` writes after two unmeasured ones; the timeline shown is the run of median length. Milliseconds from
the call's start; threads named as the pool names them.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from scenesplat_stereo.bench.scenes import PREDICTION_GAUSSIANS, synthetic_scene  # noqa: E402
from scenesplat_stereo.common.ownership import OwnedFile  # noqa: E402
from scenesplat_stereo.scene import palettes, row_tasks, sog, sog_texels  # noqa: E402
from sgmodel.bench import report  # noqa: E402

events: list[tuple[str, str, float, float]] = []  # (stage, thread, start, end), perf_counter seconds


def timed(label: str, fn):
    @functools.wraps(fn)
    def run(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            events.append((label, threading.current_thread().name, t0, time.perf_counter()))
    return run


class TimedPool(ThreadPoolExecutor):
    """The shared pool, each task timed under its function's name."""

    def submit(self, fn, /, *args, **kwargs):
        return super().submit(timed(f"task {getattr(fn, '__name__', 'task')}", fn), *args, **kwargs)


def instrument() -> None:
    """Wrap the writer's stages (module docstring) for the rest of the process."""
    palettes.codebook = timed("codebook", palettes.codebook)
    palettes.kmeans = timed("kmeans", palettes.kmeans)
    palettes.Nearest.__init__ = timed("nearest table", palettes.Nearest.__init__)
    palettes.Nearest.__call__ = timed("nearest labels", palettes.Nearest.__call__)
    for name in ("write_webp", "morton_order"):
        setattr(sog, name, timed(name, getattr(sog, name)))
    for name in ("placed", "scale_texels", "colour_texels", "pack_quats", "sh_palette"):
        setattr(sog_texels, name, timed(name, getattr(sog_texels, name)))
    row_tasks._pool = TimedPool(row_tasks.workers(), thread_name_prefix="row-tasks")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gaussians", type=int, default=PREDICTION_GAUSSIANS)
    p.add_argument("--sh-degree", type=int, default=0, choices=range(4))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    args = p.parse_args(argv)
    out = OwnedFile(args.out, "--out", "scripts/profile/sog_timeline.py")
    scene = synthetic_scene(args.gaussians, args.sh_degree)
    instrument()
    runs = []
    for i in range(args.repeats + 2):
        events.clear()
        t0 = time.perf_counter()
        sog.encode_sog(scene)
        t1 = time.perf_counter()
        if i >= 2:
            runs.append((t1 - t0, t0, list(events)))
    runs.sort(key=lambda r: r[0])
    total, t0, timeline = runs[len(runs) // 2]
    lines = [f"`sog.encode_sog` of {args.gaussians:,} Gaussians, SH {args.sh_degree}, {row_tasks.workers()} pool "
             f"threads: median {1000 * statistics.median(r[0] for r in runs):.1f} ms of {args.repeats} "
             f"(fastest {1000 * runs[0][0]:.1f}); the median run's stages, ms from its start:", "",
             "| stage | thread | start | end | ms |", "|---|---|---:|---:|---:|"]
    for label, thread, a, b in sorted(timeline, key=lambda e: (e[2], e[3])):
        lines.append(f"| {label} | {thread} | {1000 * (a - t0):.1f} | {1000 * (b - t0):.1f} | "
                     f"{1000 * (b - a):.1f} |")
    busy: dict[str, float] = {}
    for label, _, a, b in timeline:
        busy[label] = busy.get(label, 0.0) + b - a
    lines += ["", f"Whole call {1000 * total:.1f} ms; the time of each stage summed over its calls and threads:", "",
              "| stage | calls | ms |", "|---|---:|---:|"]
    for label, ms in sorted(busy.items(), key=lambda kv: -kv[1]):
        lines.append(f"| {label} | {sum(e[0] == label for e in timeline)} | {1000 * ms:.1f} |")
    report("\n".join(lines) + "\n", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
