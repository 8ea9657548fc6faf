"""Issue 9's targets on the GPU: our rasteriser against gsplat, runs interleaved, on the same tensors.

Per workload: forward ms and forward + backward ms of mean(render^2), ours and gsplat (antialiased; we pass
``max_alpha=0.999``, gsplat 1.5.3's clamp), and our compositing backward alone (cotangents of ones).
Medians (min-max) of ``--repeats`` interleaved runs after two warm-up calls each, synchronised, and the
torch allocator's peak of one more call of each above what was allocated before it. Workloads:
the model's (32 scenes x 4 targets at 256x256, SH 2, one batched call), 1M random SH3 1280x720, the
guitar teacher when ``SCENESPLAT_GUITAR_PLY`` exists, and with ``--captures DIR`` the real captures there
(``CAPTURES``, any format ``load_scene`` reads) at 1280x720, each seen by one camera and by four in one call
(an orbit around the median of the means at four azimuths, framing 80% of the means). ``--quick``: tiny
sizes, runs on the CPU too (a smoke test of this script, without gsplat).

    python3 scripts/profile/gpu_vs_gsplat.py [--quick] [--repeats N] [--captures DIR] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.bench import render_batch as rb
from scenesplat_stereo.bench.render import GUITAR, guitar_scene, identity_camera, load_gsplat, random_scene
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.raster.binning import bin_gaussians
from scenesplat_stereo.raster.composite import composite_forward
from scenesplat_stereo.raster.composite_backward import composite_backward
from scenesplat_stereo.raster.projection import project_gaussians
from scenesplat_stereo.raster.sh import eval_sh_colors
from scenesplat_stereo.scene.cameras import orbit_poses, viewmats_from_c2w
from scenesplat_stereo.scene.scene_files import load_scene

KEYS = ("means", "quats", "scales", "opacities", "colors")
#: Real captures of ``--captures`` (paths under it): a .splat of 113,648 Gaussians, the SH 3 skull (94,936), and
#: the largest SOG statue (101,275).
CAPTURES = ("plant/plant.splat", "skull/skull.sog", "statue-narcissus/narcissus.sog")


def call(impl, data, W, H, sh, grad, marks: dict | None = None):
    """One call of ``impl`` (ours or gsplat's) on the workload, with mean(render^2) backward when ``grad``;
    ``marks`` receives the host times (perf_counter) at the call and when it returned."""
    leaves = {k: data[k].detach().requires_grad_(grad) for k in KEYS}
    kw = dict(sh_degree=sh, rasterize_mode="antialiased")
    if impl is rasterization:
        kw["max_alpha"] = 0.999
    with torch.set_grad_enabled(grad):
        if marks is not None:
            marks["call"] = time.perf_counter()
        out = impl(*(leaves[k] for k in KEYS), data["viewmats"], data["Ks"], W, H, **kw)[0]
        if marks is not None:
            marks["returned"] = time.perf_counter()
        if grad:
            out.square().mean().backward()
    return leaves


def composite_bwd_fn(data, W, H, sh, ts, dev):
    """The compositing backward alone on the (flattened) workload, cotangents of ones."""
    batched = data["means"].dim() == 3
    m, q, sc, o, col = (data[k] if batched else data[k][None] for k in KEYS)
    B = m.shape[0]
    vm, Ks = data["viewmats"].reshape(B, -1, 4, 4), data["Ks"].reshape(B, -1, 3, 3)
    fns = []
    for b in range(1 if B == 1 else 2):  # two scenes are enough for the relative timing of one stage
        proj = project_gaussians(m[b], q[b], sc[b], o[b], vm[b], Ks[b], W, H, 0.01, 1e10, 0.3, True, ts)
        colors = eval_sh_colors(sh, m[b], vm[b], col[b], proj.radii)
        bins = bin_gaussians(proj, W, H, ts)
        args = (proj.means2d, proj.conics, colors, proj.opacities, bins, W, H, ts, 0.999)
        _, alphas, last = composite_forward(*args, proj.touch_extents)
        fns.append(lambda a=args, al=alphas, la=last: composite_backward(*a, al, la, torch.ones(
            *al.shape[:-1], colors.shape[-1], device=dev), torch.ones_like(al)))
    return lambda: [f() for f in fns]


def times(fns: dict, dev: str, repeats: int) -> dict[str, list[float]]:
    sync = torch.cuda.synchronize if dev.startswith("cuda") else (lambda: None)
    for fn in fns.values():
        fn(), fn()
    sync()
    out = {n: [] for n in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            sync()
            out[name].append((time.perf_counter() - t0) * 1e3)
    return out


def peaks(fns: dict, dev: str) -> dict[str, float]:
    """Torch allocator peak of one call of each, MiB above what was allocated before it (CUDA only)."""
    if not dev.startswith("cuda"):
        return {}
    out = {}
    for name, fn in fns.items():
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        fn()
        torch.cuda.synchronize()
        out[name] = (torch.cuda.max_memory_allocated() - base) / 2**20
    return out


def cell(ts):
    return f"{statistics.median(ts):.3f} ({min(ts):.3f}-{max(ts):.3f})"


def workload_rows(name, data, W, H, sh, dev, gs, repeats) -> list[str]:
    fns = {"ours forward": lambda: call(rasterization, data, W, H, sh, False),
           "ours fwd+bwd": lambda: call(rasterization, data, W, H, sh, True),
           "ours composite backward": composite_bwd_fn(data, W, H, sh, 16, dev)}
    if gs is not None:
        fns |= {"gsplat forward": lambda: call(gs, data, W, H, sh, False),
                "gsplat fwd+bwd": lambda: call(gs, data, W, H, sh, True)}
    t = times(fns, dev, repeats)
    peak = peaks(fns, dev)
    med = {k: statistics.median(v) for k, v in t.items()}
    lines = [f"#### {name}", "", "| row | ms median (min-max) | / gsplat | peak MiB |", "|---|---|---|---|"]
    for k, v in t.items():
        base = med.get("gsplat forward" if "forward" in k and "bwd" not in k else "gsplat fwd+bwd")
        ratio = f"{med[k] / base:.3f}" if base and "composite" not in k else ""
        mib = f"{peak[k]:.0f}" if k in peak else ""
        lines.append(f"| {k} | {cell(v)} | {ratio} | {mib} |")
    return lines + [""]


def script_args(doc: str, repeats: int) -> argparse.Namespace:
    """``--quick``, ``--repeats``, ``--out`` of these GPU scripts."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--repeats", type=int, default=repeats)
    p.add_argument("--out", default=None)
    p.add_argument("--captures", type=Path, default=None, help="a folder holding CAPTURES (skipped when absent)")
    return p.parse_args()


def single_scenes(quick: bool, dev: str) -> list[tuple]:
    """(name, data, W, H, sh_degree) of the single-scene workloads: 1M random SH3 at 1280x720 and the
    guitar teacher when present (``quick``: 5,000 Gaussians at 160x96, no guitar)."""
    n1m, W, H = (5000, 160, 96) if quick else (1_000_000, 1280, 720)
    vm, K = identity_camera(W, H, dev)
    work = [(f"random {n1m:,} SH3 {W}x{H}", random_scene(n1m, 3, dev) | dict(viewmats=vm, Ks=K), W, H, 3)]
    if GUITAR.exists() and not quick:
        g, gv, gK = guitar_scene(dev, W, H)
        work.append((f"guitar {g['means'].shape[0]:,} SH0 {W}x{H}", g | dict(viewmats=gv, Ks=gK), W, H, 0))
    return work


def capture_scenes(root: Path | None, dev: str, W: int = 1280, H: int = 720) -> list[tuple]:
    """(name, data, W, H, sh_degree) of each capture of ``CAPTURES`` under ``root`` that exists, seen by one
    camera and by four cameras in one call (module docstring)."""
    _, K = identity_camera(W, H, dev)
    work = []
    for rel in CAPTURES if root is not None else ():
        if not (root / rel).exists():
            continue
        scene = load_scene(root / rel)
        center = np.median(scene.means, axis=0)
        radius = float(np.quantile(np.linalg.norm(scene.means - center, axis=1), 0.8))
        distance = radius * float(K[0, 1, 1]) / (0.5 * H)  # the radius fills half the image's height
        # a quarter turn apart, the first looking along +z, 0.3 of the distance above the centre (y down)
        poses = orbit_poses(center, distance * math.hypot(1.0, 0.3), 4, math.degrees(math.atan(0.3)))
        vm = torch.tensor(viewmats_from_c2w(np.roll(poses, 1, axis=0)), dtype=torch.float32, device=dev)
        data = scene.to_torch(dev)
        for cams in (1, 4):
            work.append((f"{Path(rel).name} {len(scene):,} SH{scene.sh_degree} {W}x{H}, {cams} camera(s)",
                         data | dict(viewmats=vm[:cams], Ks=K.expand(cams, 3, 3).contiguous()), W, H,
                         scene.sh_degree))
    return work


def report(title: str, work: list[tuple], rows, dev: str, repeats: int, out: str | None) -> None:
    """Print ``rows(*workload, dev, gsplat, repeats)`` (markdown lines) per workload under ``title``
    (followed by the device and the repeats), and write them all to ``out`` when given."""
    gs = load_gsplat() if dev == "cuda" else None
    name = torch.cuda.get_device_name() if dev == "cuda" else "CPU"
    lines = [f"### {title} ({name}, {repeats} interleaved runs)", ""]
    for w in work:
        block = rows(*w, dev, gs, repeats)
        lines += block
        print("\n".join(block), flush=True)
    if out:
        with open(out, "w") as f:
            f.write("\n".join(lines) + "\n")


def main() -> int:
    a = script_args(__doc__, 20)
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    scenes, side = (2, 32) if a.quick else (32, 256)
    work = [(f"model: {scenes} scenes x 4 targets {side}x{side}, SH 2, batched", rb.workload(scenes, side, dev),
             side, side, rb.SH_DEGREE), *single_scenes(a.quick, dev), *capture_scenes(a.captures, dev)]
    report("Ours against gsplat", work, workload_rows, dev, a.repeats, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
