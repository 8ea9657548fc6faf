"""The dataset build on 1, 2, 4 ... GPUs of one host through its Ray backend (``scripts/gpu/scale.sh build``).

    python scripts/checks/ray_build_scale.py --teachers DIR --work DIR --gpus 1 2 4 [--device cuda] [--out report.md]
                                      [-- extra `scenesplat-stereo build` flags]

For each count K, ``scenesplat-stereo build --backend ray --ray-address local`` with ``CUDA_VISIBLE_DEVICES``
set to the first K GPUs: Ray starts a cluster of this host that sees K GPUs and runs one task per teacher,
one GPU each (``build._run_ray``), so K teachers render at a time. Each K builds into a fresh folder (removed
afterwards). Throughput is the build's own count: pairs written over its wall time (Ray's start-up, some
seconds, included), and over the teachers' window: from the first task's start to the last one's end
(Ray's start-up and its workers' imports left out; what a long build sees). The speed-up is from the
window. On ``--device cpu`` (a dry run) Ray sees the host's CPUs and K only names the run.

The projection: the paper's training set (appendix B; ``scenesplat_stereo.bench.build.PAPER_TRAIN_PAIRS``,
pairs of 12 images at two sizes) at the largest K's rate, the rate scaled by pixel count from the size
built here (``--resolution`` among the extra flags) to each paper size, as ``bench build`` does for a size
it did not measure.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import parse_size
from sgmodel.bench import report

REPO = Path(__file__).resolve().parents[2]
RATE = re.compile(r"wall ([0-9.]+) s \(([0-9.]+) pairs/s.*start to last one's end ([0-9.]+) s \(([0-9.]+) pairs/s\)"
                  r"; [0-9]+ teachers in ([0-9]+) processes")


def build_once(gpus: int, teachers: Path, out: Path, device: str, extra: list[str]) -> tuple[float, ...]:
    """(wall s, pairs/s, teachers' window s, pairs/s in it, worker processes) of one Ray build on the first
    ``gpus`` GPUs; RuntimeError with its output if it fails."""
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    if device.startswith("cuda"):
        env["CUDA_VISIBLE_DEVICES"] = ",".join(str(i) for i in range(gpus))
    cmd = [sys.executable, "-m", "scenesplat_stereo.cli", "build", "--teachers", str(teachers), "--out", str(out),
           "--backend", "ray", "--ray-address", "local", "--device", device, "--no-progress", *extra]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env)
    found = RATE.search(done.stdout)
    if done.returncode != 0 or found is None:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}")
    return tuple(float(v) for v in found.groups())


def resolution(extra: list[str]) -> tuple[int, int] | None:
    """The ``--resolution WxH`` among the build flags (``common.text.parse_size``), or None."""
    return parse_size(extra[extra.index("--resolution") + 1], "--resolution") if "--resolution" in extra else None


def main(argv: list[str] | None = None) -> int:
    from scenesplat_stereo.bench.build import PAPER_TRAIN_PAIRS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument("--teachers", type=Path, required=True, help="teacher scenes (e.g. `demo-teachers`)")
    p.add_argument("--work", type=Path, required=True, help="folder for the builds (created)")
    p.add_argument("--gpus", type=int, nargs="+", default=[1, 2, 4], help="GPU counts (default 1 2 4)")
    p.add_argument("--device", default="cuda", help="cuda, or cpu for a dry run")
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    p.add_argument("extra", nargs=argparse.REMAINDER, help="after --: more `scenesplat-stereo build` flags")
    args = p.parse_args(argv)
    report_out = OwnedFile(args.out, "--out", "scripts/checks/ray_build_scale.py")  # before any build
    extra = args.extra[1:] if args.extra[:1] == ["--"] else args.extra
    rows = {}
    for k in args.gpus:
        out = args.work / f"gpus{k}"
        shutil.rmtree(out, ignore_errors=True)
        rows[k] = build_once(k, args.teachers, out, args.device, extra)
        shutil.rmtree(out, ignore_errors=True)
    base = rows[args.gpus[0]][3] / args.gpus[0]  # pairs/s per GPU of the first count (1 GPU: measured)
    lines = [f"`scenesplat-stereo build --backend ray` on {args.device}, flags `{' '.join(extra)}`; wall: the "
             f"command (Ray's start-up included); window: the first teacher's start to the last one's end:", "",
             "| GPUs | wall (s) | pairs/s (wall) | window (s) | pairs/s (window) | speed-up (window) | processes |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {k} | {wall:.1f} | {pps:.1f} | {span:.1f} | {rate:.1f} | {rate / base:.2f} | {procs:.0f} |"
              for k, (wall, pps, span, rate, procs) in rows.items()]
    size = resolution(extra)
    if size is not None:
        k = args.gpus[-1]
        rate = rows[k][3]
        hours = sum(n / (rate * size[0] * size[1] / (w * h)) / 3600 for (w, h), n in PAPER_TRAIN_PAIRS.items())
        lines += ["", f"The paper's training set ({sum(PAPER_TRAIN_PAIRS.values()):,} pairs x 12 images at "
                  f"{', '.join(f'{w}x{h}' for w, h in PAPER_TRAIN_PAIRS)}) on {k} GPUs of this host, from "
                  f"{rate:.1f} pairs/s at {size[0]}x{size[1]} scaled by pixel count: **{hours:.2f} h**."]
    report("\n".join(lines) + "\n", report_out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
