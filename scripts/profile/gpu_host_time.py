"""Host or GPU: where a single frame's time goes, ours against gsplat (issue 9's diagnosis).

Per workload (1M random Gaussians SH3 at 1280x720, the guitar teacher when ``SCENESPLAT_GUITAR_PLY`` exists,
and with ``--captures DIR`` the real captures of ``gpu_vs_gsplat.py``), forward and forward + backward of ours
and gsplat's, runs interleaved: the wall time (synchronised) and the host time until the call returns; our
forward's host time split at the binning's one host sync (before it, the binning after it, the compositing
launch to the return); and the GPU's busy time per call (the union of kernel intervals that ``torch.profiler``
records) with the longest kernels. When the host time approaches the wall time, the GPU is waiting for the
host. ``--quick``: tiny sizes, runs on the CPU too (a smoke test of this script, without gsplat or the
profiler table).

    python3 scripts/profile/gpu_host_time.py [--quick] [--repeats N] [--captures DIR] [--out FILE.md]
"""

from __future__ import annotations

import collections
import statistics
import sys
import time

import torch
from gpu_vs_gsplat import call, capture_scenes, report, script_args, single_scenes

import scenesplat_stereo.raster.rendering as rendering
from scenesplat_stereo.raster import rasterization

_marks: dict[str, float] = {}


def _timed_finish(pending):
    """``finish_binning`` with timestamps: when the host reaches the sync, and when the binning returns."""
    _marks["sync"] = time.perf_counter()
    bins = _FINISH(pending)
    _marks["binned"] = time.perf_counter()
    return bins


_FINISH = rendering.finish_binning


def ms(values) -> str:
    return f"{statistics.median(values) * 1e3:.3f}"


def gpu_busy(fn, iters: int = 10) -> tuple[float, list[tuple[float, str]]]:
    """(ms of GPU busy time per call, [(us per call, kernel name)] longest first) from torch.profiler."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(iters):
            fn()
            torch.cuda.synchronize()
    events = [e for e in prof.profiler.kineto_results.events() if e.device_type() == torch.autograd.DeviceType.CUDA]
    busy, end = 0, None
    for s, e in sorted((e.start_ns(), e.start_ns() + e.duration_ns()) for e in events):
        if end is None or s > end:
            busy, end = busy + (e - s), e
        elif e > end:
            busy, end = busy + (e - end), e
    per = collections.defaultdict(float)
    for e in events:
        per[e.name()[:80]] += e.duration_ns()
    return busy / iters / 1e6, sorted(((v / iters / 1e3, k) for k, v in per.items()), reverse=True)[:6]


def workload(name, data, W, H, sh, dev, gs, repeats) -> list[str]:
    fns = {"ours forward": lambda: call(rasterization, data, W, H, sh, False, _marks),
           "ours fwd+bwd": lambda: call(rasterization, data, W, H, sh, True, _marks)}
    if gs is not None:
        fns |= {"gsplat forward": lambda: call(gs, data, W, H, sh, False, _marks),
                "gsplat fwd+bwd": lambda: call(gs, data, W, H, sh, True, _marks)}
    sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
    for fn in fns.values():
        fn(), fn()
    wall, host, split = collections.defaultdict(list), collections.defaultdict(list), collections.defaultdict(list)
    rendering.finish_binning = _timed_finish
    try:
        for _ in range(repeats):
            for n, fn in fns.items():
                sync()
                t0 = time.perf_counter()
                fn()
                sync()
                wall[n].append(time.perf_counter() - t0)
                host[n].append(_marks["returned"] - _marks["call"])
                if n == "ours forward":
                    split["before the sync"].append(_marks["sync"] - _marks["call"])
                    split["binning after it"].append(_marks["binned"] - _marks["sync"])
                    split["compositing launch to return"].append(_marks["returned"] - _marks["binned"])
    finally:
        rendering.finish_binning = _FINISH
    lines = [f"#### {name}", "", "| row | wall ms | host call ms | GPU busy ms |", "|---|---|---|---|"]
    tables = []
    for n, fn in fns.items():
        busy, top = gpu_busy(fn) if dev == "cuda" else (None, [])
        lines.append(f"| {n} | {ms(wall[n])} | {ms(host[n])} | {'' if busy is None else f'{busy:.3f}'} |")
        tables += [f"{n}: " + "; ".join(f"{us:.1f} us {k}" for us, k in top)] if top else []
    lines += ["", "Our forward's host time: " + ", ".join(f"{k} {ms(v)} ms" for k, v in split.items()) + "."]
    return lines + ["", *(f"- {t}" for t in tables), ""]


def main() -> int:
    a = script_args(__doc__, 30)
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    work = [*single_scenes(a.quick, dev)[::-1], *capture_scenes(a.captures, dev)]  # the guitar first
    report("Host time against GPU time, medians", work, workload, dev, a.repeats, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
