"""Host or GPU: where a single frame's time goes, ours against gsplat (issue 9's diagnosis).

Per workload (1M random Gaussians SH3 at 1280x720, and the guitar teacher when ``SCENESPLAT_GUITAR_PLY``
exists), forward and forward + backward of ours and gsplat's, runs interleaved: the wall time (synchronised)
and the host time until the call returns; our forward's host time split at the binning's one host sync
(before it, the binning after it, the compositing launch to the return); and the GPU's busy time per call
(the union of kernel intervals that ``torch.profiler`` records) with the longest kernels. When the host
time approaches the wall time, the GPU is waiting for the host. ``--quick``: tiny sizes, runs on the CPU
too (a smoke test of this script, without gsplat or the profiler table).

    python3 scripts/gpu_host_time.py [--quick] [--repeats N] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import collections
import statistics
import sys
import time

import torch

import scenesplat_stereo.raster.rendering as rendering
from scenesplat_stereo.bench.render import GUITAR, guitar_scene, identity_camera, load_gsplat, random_scene
from scenesplat_stereo.raster import rasterization

KEYS = ("means", "quats", "scales", "opacities", "colors")
_marks: dict[str, float] = {}


def _timed_finish(pending):
    """``finish_binning`` with timestamps: when the host reaches the sync, and when the binning returns."""
    _marks["sync"] = time.perf_counter()
    bins = _FINISH(pending)
    _marks["binned"] = time.perf_counter()
    return bins


_FINISH = rendering.finish_binning


def call(impl, data, W, H, sh, grad):
    leaves = {k: data[k].detach().requires_grad_(grad) for k in KEYS}
    kw = dict(sh_degree=sh, rasterize_mode="antialiased")
    if impl is rasterization:
        kw["max_alpha"] = 0.999
    with torch.set_grad_enabled(grad):
        _marks["call"] = time.perf_counter()
        out = impl(*(leaves[k] for k in KEYS), data["viewmats"], data["Ks"], W, H, **kw)[0]
        _marks["returned"] = time.perf_counter()
        if grad:
            out.square().mean().backward()


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
    fns = {"ours forward": lambda: call(rasterization, data, W, H, sh, False),
           "ours fwd+bwd": lambda: call(rasterization, data, W, H, sh, True)}
    if gs is not None:
        fns |= {"gsplat forward": lambda: call(gs, data, W, H, sh, False),
                "gsplat fwd+bwd": lambda: call(gs, data, W, H, sh, True)}
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
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    gs = load_gsplat() if dev == "cuda" else None
    n1m, W, H = (5000, 160, 96) if a.quick else (1_000_000, 1280, 720)
    vm, K = identity_camera(W, H, dev)
    work = [(f"random {n1m:,} SH3 {W}x{H}", random_scene(n1m, 3, dev) | dict(viewmats=vm, Ks=K), W, H, 3)]
    if GUITAR.exists() and not a.quick:
        g, gv, gK = guitar_scene(dev, W, H)
        work.insert(0, (f"guitar {g['means'].shape[0]:,} SH0 {W}x{H}", g | dict(viewmats=gv, Ks=gK), W, H, 0))
    name = torch.cuda.get_device_name() if dev == "cuda" else "CPU"
    lines = [f"### Host time against GPU time ({name}, {a.repeats} interleaved runs, medians)", ""]
    for w in work:
        block = workload(*w, dev, gs, a.repeats)
        lines += block
        print("\n".join(block), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
