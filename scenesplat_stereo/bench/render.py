"""``scenesplat-stereo bench render``: what the rasteriser's accuracy knobs cost in time.

Prints markdown tables (paste-ready for docs/benchmarks.md):
1. the headline workloads (1M random Gaussians, SH degree 3, and the guitar teacher, both 1280x720,
   antialiased) against gsplat 1.5.3's ``rasterization`` on the same inputs (when gsplat is importable);
2. one-knob-at-a-time sweeps from a base setting (tile size, SH degree, rasterize mode, render mode,
   resolution, number of Gaussians): median ms per frame, PSNR against gsplat at the timed size, and PSNR
   against the float64 reference (``scenesplat_stereo.raster.reference``) on a small frame;
3. with ``--backward``: forward+backward time and peak memory against gsplat, for the two headline
   workloads and the model's (32 scenes x 4 targets at 256x256, 2 x 288^2 Gaussians per scene).
With ``--batch``, only the model's workload instead, one batched call against a loop of calls, ours and
gsplat's, forward and forward + backward (see ``bench/render_batch.py``).
Times are medians of ``--repeats`` runs after warm-up, synchronised on CUDA. Peak memory is torch's
allocator peak (Warp's radix-sort scratch is outside it, a few bytes per intersection).
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.bench.render_batch import batch_table
from scenesplat_stereo.common.commandline import Parser, run_command
from scenesplat_stereo.common.measure import median_seconds, psnr_from_mse
from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.raster.reference import as_renderer_sees, reference_rasterization
from scenesplat_stereo.scene.cameras import look_at, viewmats_from_c2w

OWNER = "scenesplat-stereo bench render"  # recorded beside --out (also as python -m): a rerun may replace it
# The real guitar teacher beside a checkout (../shared/data), or where SCENESPLAT_GUITAR_PLY points.
GUITAR = Path(os.environ.get("SCENESPLAT_GUITAR_PLY", Path(__file__).resolve().parents[2].parent
                             / "shared/data/teachers/playcanvas-guitar/point_cloud.ply"))


@dataclass(frozen=True)
class Setting:
    """One benchmark configuration (gsplat argument names)."""

    n: int = 200_000
    width: int = 1280
    height: int = 720
    sh_degree: int = 3
    rasterize_mode: str = "antialiased"
    render_mode: str = "RGB"
    tile_size: int = 16


def random_scene(n: int, sh_degree: int, device: str, seed: int = 0) -> dict:
    """n Gaussians in the frustum of an identity camera (z in [2, 12]), gsplat-style tensors."""
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 10.0 * torch.rand(n, generator=g)
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * torch.stack([0.7 * z, 0.4 * z], -1)
    K = (sh_degree + 1) ** 2
    sh = torch.randn(n, K, 3, generator=g) * 0.15
    sh[:, 0] = (torch.rand(n, 3, generator=g) - 0.5) * 3.0
    scene = dict(
        means=torch.cat([xy, z[:, None]], -1),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.exp(torch.empty(n, 3).uniform_(math.log(0.004), math.log(0.04), generator=g)),
        opacities=0.1 + 0.9 * torch.rand(n, generator=g),
        colors=sh,
    )
    return {k: v.to(device) for k, v in scene.items()}


def identity_camera(width: int, height: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    f = 0.5 * width / math.tan(math.radians(35.0))
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32)
    return torch.eye(4, device=device)[None], K.to(device)[None]


def guitar_scene(device: str, width: int, height: int) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The real guitar teacher and an orbit camera (radius 6 around the median of the means, y down)."""
    from scenesplat_stereo.scene.gaussians import load_ply

    scene = load_ply(GUITAR)
    center = np.median(scene.means, axis=0)
    c2w = look_at(center + np.array([0.0, -2.0, -5.6]), center)
    viewmats = torch.tensor(viewmats_from_c2w(c2w), dtype=torch.float32)[None]
    _, K = identity_camera(width, height, "cpu")
    return scene.to_torch(device), viewmats.to(device), K.to(device)


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR (dB, range 1) of two renders, in float64, unclipped."""
    return psnr_from_mse(float(((a.double() - b.double()) ** 2).mean()))


def _render_fn(impl, scene, viewmats, Ks, s: Setting, max_alpha: float, deterministic: bool = False):
    kw = dict(sh_degree=s.sh_degree, render_mode=s.render_mode, rasterize_mode=s.rasterize_mode,
              tile_size=s.tile_size)
    if impl is rasterization:
        kw["max_alpha"] = max_alpha
        kw["deterministic"] = deterministic
    return lambda: impl(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                        viewmats, Ks, s.width, s.height, **kw)


def load_gsplat():
    """gsplat's ``rasterization`` when gsplat is installed, else None."""
    if importlib.util.find_spec("gsplat") is None:
        return None
    from gsplat import rasterization as gs_rasterization

    return gs_rasterization


def _fmt(x: float, digits: int = 1) -> str:
    return "n/a" if x is None else ("inf" if math.isinf(x) else f"{x:.{digits}f}")


def reference_psnr(s: Setting, device: str, seed: int = 1) -> float:
    """PSNR of our float32 render (on ``device``) against the float64 reference (on the CPU) on a small
    frame of the same setting; the reference gets the float parameters rounded to float32 as the tests do
    (``reference.as_renderer_sees``)."""
    small = replace(s, n=3000, width=max(8, s.width // 8), height=max(8, s.height // 8))
    scene = random_scene(small.n, s.sh_degree, "cpu", seed)
    viewmats, Ks = identity_camera(small.width, small.height, "cpu")
    on_device = {k: v.to(device) for k, v in scene.items()}
    ours = _render_fn(rasterization, on_device, viewmats.to(device), Ks.to(device), small, 0.99)()[0].cpu()
    d64 = {k: v.double() for k, v in scene.items()}
    ref = reference_rasterization(d64["means"], d64["quats"], d64["scales"], d64["opacities"], d64["colors"],
                    viewmats.double(), Ks.double(), small.width, small.height,
                    **as_renderer_sees(dict(sh_degree=s.sh_degree, render_mode=s.render_mode,
                                            rasterize_mode=s.rasterize_mode, tile_size=s.tile_size,
                                            max_alpha=0.99)))[0]
    return psnr(ours[..., :3], ref[..., :3])


def sweep_rows(base: Setting, quick: bool) -> list[tuple[str, Setting]]:
    """One-knob-at-a-time variations of the base setting."""
    rows = [("base", base)]
    rows += [(f"tile_size={t}", replace(base, tile_size=t)) for t in (8, 32)]
    rows += [(f"sh_degree={d}", replace(base, sh_degree=d)) for d in (0, 1, 2) if d != base.sh_degree]
    rows += [("classic", replace(base, rasterize_mode="classic"))]
    rows += [(f"render_mode={m}", replace(base, render_mode=m)) for m in ("RGB+D", "RGB+ED", "D")]
    scale = (0.25, 0.5, 2.0) if not quick else (0.5, 2.0)
    rows += [(f"{int(base.width * f)}x{int(base.height * f)}", replace(base, width=int(base.width * f),
              height=int(base.height * f))) for f in scale]
    rows += [(f"n={int(base.n * f):,}", replace(base, n=int(base.n * f))) for f in (0.25, 4.0)]
    return rows


def headline(args, gs) -> list[str]:
    device = args.device
    out = ["| workload | ours ms | gsplat ms | ratio | PSNR vs gsplat (dB) |", "|---|---|---|---|---|"]
    workloads = []
    s = Setting(n=args.headline_n, width=args.width, height=args.height)
    scene = random_scene(s.n, 3, device)
    workloads.append((f"random {s.n:,} SH3 {s.width}x{s.height}", scene, *identity_camera(s.width, s.height, device), s))
    if GUITAR.exists():
        gscene, gv, gK = guitar_scene(device, args.width, args.height)
        workloads.append((f"guitar teacher {gscene['means'].shape[0]:,} SH0 {args.width}x{args.height}", gscene,
                          gv, gK, replace(s, n=gscene["means"].shape[0], sh_degree=0)))
    for name, scene, viewmats, Ks, st in workloads:
        ours = _render_fn(rasterization, scene, viewmats, Ks, st, 0.999)
        t_ours = median_seconds(ours, device, args.repeats)
        t_gs = p = None
        if gs is not None:
            theirs = _render_fn(gs, scene, viewmats, Ks, st, 0.999)
            t_gs = median_seconds(theirs, device, args.repeats)
            p = psnr(ours()[0], theirs()[0])
        ratio = None if t_gs is None else t_ours / t_gs
        out.append(f"| {name} | {_fmt(t_ours * 1e3, 2)} | {_fmt(t_gs and t_gs * 1e3, 2)} | {_fmt(ratio, 2)} | {_fmt(p)} |")
    return out


def sweeps(args, gs) -> list[str]:
    device = args.device
    base = Setting(n=args.sweep_n, width=args.width, height=args.height)
    out = ["| setting | N | size | ours ms/frame | gsplat ms/frame | PSNR vs gsplat (dB) | PSNR vs float64 ref, small frame (dB) |",
           "|---|---|---|---|---|---|---|"]
    scenes: dict[tuple[int, int], dict] = {}
    for name, s in sweep_rows(base, args.quick):
        key = (s.n, s.sh_degree)
        if key not in scenes:
            scenes[key] = random_scene(s.n, s.sh_degree, device)
        viewmats, Ks = identity_camera(s.width, s.height, device)
        ours = _render_fn(rasterization, scenes[key], viewmats, Ks, s, 0.999)
        t = median_seconds(ours, device, args.repeats)
        t_gs = p = None
        if gs is not None:
            theirs = _render_fn(gs, scenes[key], viewmats, Ks, s, 0.999)
            t_gs = median_seconds(theirs, device, args.repeats)
            p = psnr(ours()[0][..., :3], theirs()[0][..., :3])
        pref = reference_psnr(s, device)
        out.append(f"| {name} | {s.n:,} | {s.width}x{s.height} | {_fmt(t * 1e3, 2)} | "
                   f"{_fmt(t_gs and t_gs * 1e3, 2)} | {_fmt(p)} | {_fmt(pref)} |")
    return out


def _fwd_bwd(impl, scenes, viewmats, Ks, s: Setting, device: str, max_alpha: float, repeats: int,
             deterministic: bool = False):
    """Median time of forward + backward of sum(render^2) over all scenes, and the peak memory in MiB."""
    def step():
        for scene in scenes:
            leaves = {k: v.detach().requires_grad_(True) for k, v in scene.items()}
            render = _render_fn(impl, leaves, viewmats, Ks, s, max_alpha, deterministic)()[0]
            render.square().mean().backward()
    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
    t = median_seconds(step, device, repeats)
    return t, (torch.cuda.max_memory_allocated() / 2**20 if cuda else None)


def backward_rows(args, gs) -> list[str]:
    device = args.device
    out = ["| workload | ours fwd+bwd ms | gsplat fwd+bwd ms | ratio | ours peak MiB | gsplat peak MiB | "
           "ours deterministic ms | deterministic peak MiB |",
           "|---|---|---|---|---|---|---|---|"]
    s = Setting(n=args.headline_n, width=args.width, height=args.height)
    workloads = [(f"random {s.n:,} SH3 {s.width}x{s.height}", [random_scene(s.n, 3, device)],
                  *identity_camera(s.width, s.height, device), s)]
    if GUITAR.exists():
        gscene, gv, gK = guitar_scene(device, args.width, args.height)
        workloads.append(("guitar teacher", [gscene], gv, gK, replace(s, sh_degree=0)))
    side = args.model_size
    per_scene = 2 * (side + 32) ** 2
    m = Setting(n=per_scene, width=side, height=side, sh_degree=0)
    model_scenes = [random_scene(per_scene, 0, device, seed=i) for i in range(args.model_scenes)]
    vm, Km = identity_camera(side, side, device)
    offsets = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [-0.05, 0.02, 0.0], [0.0, -0.05, 0.03]], device=device)
    vm4 = vm.repeat(4, 1, 1)
    vm4[:, :3, 3] = offsets
    workloads.append((f"model: {args.model_scenes} scenes x 4 targets {side}x{side}, {per_scene:,} G/scene",
                      model_scenes, vm4, Km.repeat(4, 1, 1), m))
    for name, scenes, viewmats, Ks, st in workloads:
        t, mem = _fwd_bwd(rasterization, scenes, viewmats, Ks, st, device, 0.999, args.repeats)
        t_det, mem_det = _fwd_bwd(rasterization, scenes, viewmats, Ks, st, device, 0.999, args.repeats, True)
        t_gs = mem_gs = None
        if gs is not None:
            t_gs, mem_gs = _fwd_bwd(gs, scenes, viewmats, Ks, st, device, 0.999, args.repeats)
        ratio = None if t_gs is None else t / t_gs
        out.append(f"| {name} | {_fmt(t * 1e3, 2)} | {_fmt(t_gs and t_gs * 1e3, 2)} | {_fmt(ratio, 2)} | "
                   f"{_fmt(mem, 0)} | {_fmt(mem_gs, 0)} | {_fmt(t_det * 1e3, 2)} | {_fmt(mem_det, 0)} |")
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cpu or cuda")
    p.add_argument("--quick", action="store_true", help="small sizes (for a CPU): 200k -> 20k Gaussians, 320x180")
    p.add_argument("--repeats", type=int, default=None, help="timed runs per row (median); default 10 on CUDA, 3 on CPU")
    p.add_argument("--backward", action="store_true", help="also time forward+backward and peak memory")
    p.add_argument("--batch", action="store_true",
                   help="only the model workload (32 scenes x 4 targets at 256x256; --quick: 2 scenes at 16x16): "
                        "batched vs looped calls, ours and gsplat, forward and forward+backward; default 20 "
                        "repeats (--quick: 3), interleaved")
    p.add_argument("--no-gsplat", action="store_true", help="do not compare with gsplat even if installed")
    p.add_argument("--out", type=Path, default=None, help="also write the markdown tables to this file (a report "
                   "of an earlier run of this bench is replaced, any other file refused)")


def run(args: argparse.Namespace) -> int:
    out = OwnedFile(args.out, "--out", OWNER)  # before any work
    if args.batch:
        return run_batch(args, out)
    quick = args.quick or args.device == "cpu"
    args.quick = quick
    args.repeats = args.repeats or (3 if quick else 10)
    args.width, args.height = (320, 180) if quick else (1280, 720)
    args.headline_n = 50_000 if quick else 1_000_000
    args.sweep_n = 20_000 if quick else 200_000
    args.model_size, args.model_scenes = (64, 2) if quick else (256, 32)
    gs = None if args.no_gsplat else load_gsplat()
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"CPU ({torch.get_num_threads()} threads)"
    lines = [f"Device: {name}; gsplat: {'1.5.3 (rasterization, max_alpha 0.999 on our side)' if gs else 'not installed'}; "
             f"median of {args.repeats} runs.", "", "### Headline workloads (forward)", ""]
    lines += headline(args, gs)
    lines += ["", "### One knob at a time (forward)", ""]
    lines += sweeps(args, gs)
    if args.backward:
        lines += ["", "### Forward + backward", ""]
        lines += backward_rows(args, gs)
    text = "\n".join(lines)
    print(text)
    out.write(text + "\n")
    return 0


def run_batch(args: argparse.Namespace, out: OwnedFile) -> int:
    """``--batch``: the model workload table only."""
    args.repeats = args.repeats or (3 if args.quick else 20)
    args.batch_scenes, args.batch_side = (2, 16) if args.quick else (32, 256)
    gs = None if args.no_gsplat else load_gsplat()
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"CPU ({torch.get_num_threads()} threads)"
    lines = [f"Device: {name}; gsplat: {'installed' if gs else 'not installed'}.", "",
             "### Model workload: batched against looped", ""] + batch_table(args, gs)
    text = "\n".join(lines)
    print(text)
    out.write(text + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m scenesplat_stereo.bench.render``: the same as ``scenesplat-stereo bench render``, with no
    import of the dataset rooms (for GPU machines that lack OpenImageIO)."""
    parser = Parser(prog="bench render", description=__doc__,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    parser.set_defaults(func=run)
    return run_command(parser, argv)  # errors as the command's: one line, exit 2 for a refused --out


if __name__ == "__main__":
    raise SystemExit(main())
