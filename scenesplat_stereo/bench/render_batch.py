"""``bench render --batch``: the model's rendering workload, one batched call against a loop of calls.

Workload (SPEC section 7, the model): ``--scenes`` scenes (32) rendered into 4 target views each at S x S
(256 x 256), SH degree 2, antialiased. Each scene looks like the composer's output: two layers of
Gaussians on the pixel grid of a reference camera padded by 16 px on each side ((S + 32)^2 per layer,
2 x 288^2 = 165,888 per scene), at depths 1-5 m, with scales of about one pixel's footprint (z / f) and a
random orientation; targets lie within 0.3 m of the reference camera and turn by up to 3 degrees.

Rows: ours batched (one ``rasterization`` call with batch dimensions ``[B, N, ...]`` / ``[B, 4, 4, 4]``),
ours looped (one call per scene, outputs stacked), ours batched with ``deterministic=True``, and, when
gsplat is importable, gsplat batched and looped on the same tensors. Forward runs under ``no_grad``;
forward + backward takes the gradient of mean(render^2) with respect to every Gaussian parameter (one
backward for the whole batch, looped or not). Runs are interleaved (each repetition times every row once,
in turn), after two warm-up runs per row; each cell is the median and (min-max) over ``--repeats`` runs,
synchronised on CUDA. Peak memory is torch's allocator peak above the inputs during one run (CUDA only;
Warp's radix-sort scratch is outside it).
"""

from __future__ import annotations

import argparse
import math
import statistics

import torch

from scenesplat_stereo.common.measure import synced_clock, synchronize
from scenesplat_stereo.raster import rasterization

# SPEC section 7: the canvas extends the S x S reference image by 16 px on each side; two layers per pixel.
CANVAS_PADDING_PX = 16
LAYERS = 2
TARGETS = 4
TARGET_RADIUS_M = 0.3
SH_DEGREE = 2
MAX_ALPHA = 0.999  # gsplat 1.5.3's alpha clamp, so that both render the same image


def reference_intrinsics(side: int) -> torch.Tensor:
    """K [3, 3] of the S x S reference camera: 60 degree horizontal field of view, centred."""
    f = 0.5 * side / math.tan(math.radians(30.0))
    return torch.tensor([[f, 0.0, side / 2], [0.0, f, side / 2], [0.0, 0.0, 1.0]])


def model_scene(side: int, seed: int) -> dict[str, torch.Tensor]:
    """One composer-like scene in the reference camera's frame (identity world-to-camera), float32 CPU."""
    g = torch.Generator().manual_seed(seed)
    K = reference_intrinsics(side)
    span = torch.arange(-CANVAS_PADDING_PX, side + CANVAS_PADDING_PX, dtype=torch.float32) + 0.5
    v, u = torch.meshgrid(span, span, indexing="ij")
    pix = torch.stack([u.reshape(-1), v.reshape(-1)], -1).repeat(LAYERS, 1)
    n = pix.shape[0]
    # Front layer: a smooth surface at 1-4 m; back layer: up to 1 m behind it; a little per-pixel jitter.
    grid = pix[: n // LAYERS]
    front = 2.5 + 1.5 * torch.sin(grid[:, 0] / 37.0 + seed) * torch.cos(grid[:, 1] / 29.0)
    z = torch.cat([front, front + torch.rand(n // LAYERS, generator=g)]) + 0.02 * torch.rand(n, generator=g)
    z = z.clamp(1.0, 5.0)
    means = torch.stack([(pix[:, 0] - K[0, 2]) / K[0, 0] * z, (pix[:, 1] - K[1, 2]) / K[1, 1] * z, z], -1)
    footprint = z / K[0, 0]  # metres per pixel at depth z
    scales = footprint[:, None] * torch.empty(n, 3).uniform_(0.4, 1.2, generator=g)
    sh = 0.1 * torch.randn(n, (SH_DEGREE + 1) ** 2, 3, generator=g)
    sh[:, 0] = (torch.rand(n, 3, generator=g) - 0.5) / 0.28209479177387814  # DC: colours in [0, 1]
    return dict(means=means, quats=torch.randn(n, 4, generator=g), scales=scales,
                opacities=torch.empty(n).uniform_(0.3, 1.0, generator=g), colors=sh)


def target_viewmats(seed: int) -> torch.Tensor:
    """[T, 4, 4] world(=reference camera)-to-target: centres within 0.3 m, turned by up to 3 degrees."""
    g = torch.Generator().manual_seed(10_000 + seed)
    out = torch.eye(4).repeat(TARGETS, 1, 1)
    for t in range(TARGETS):
        axis = torch.nn.functional.normalize(torch.randn(3, generator=g), dim=0)
        angle = math.radians(3.0) * float(torch.rand(1, generator=g))
        x, y, z = axis.tolist()
        skew = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
        R = torch.eye(3) + math.sin(angle) * skew + (1 - math.cos(angle)) * skew @ skew
        centre = torch.nn.functional.normalize(torch.randn(3, generator=g), dim=0) * TARGET_RADIUS_M * float(
            torch.rand(1, generator=g))
        out[t, :3, :3] = R
        out[t, :3, 3] = -R @ centre
    return out


def workload(n_scenes: int, side: int, device: str) -> dict[str, torch.Tensor]:
    """Batched tensors: Gaussians [B, N, ...], viewmats [B, T, 4, 4], Ks [B, T, 3, 3]."""
    scenes = [model_scene(side, b) for b in range(n_scenes)]
    batch = {k: torch.stack([s[k] for s in scenes]) for k in scenes[0]}
    batch["viewmats"] = torch.stack([target_viewmats(b) for b in range(n_scenes)])
    batch["Ks"] = reference_intrinsics(side).expand(n_scenes, TARGETS, 3, 3).contiguous()
    return {k: v.to(device) for k, v in batch.items()}


GAUSSIAN_KEYS = ("means", "quats", "scales", "opacities", "colors")


def _call(impl, data: dict, side: int, deterministic: bool):
    kw = dict(sh_degree=SH_DEGREE, rasterize_mode="antialiased")
    if impl is rasterization:
        kw |= dict(max_alpha=MAX_ALPHA, deterministic=deterministic)
    return impl(*(data[k] for k in GAUSSIAN_KEYS), data["viewmats"], data["Ks"], side, side, **kw)[0]


def render_fn(impl, data: dict, side: int, looped: bool, backward: bool, deterministic: bool = False):
    """A closure that renders the whole workload once (and back-propagates when ``backward``); returns the
    rendered images [B, T, S, S, 3]."""
    def run():
        leaves = {k: v.detach().requires_grad_(backward) if k in GAUSSIAN_KEYS else v for k, v in data.items()}
        with torch.set_grad_enabled(backward):
            if looped:
                render = torch.stack([_call(impl, {k: v[b] for k, v in leaves.items()}, side, deterministic)
                                      for b in range(data["means"].shape[0])])
            else:
                render = _call(impl, leaves, side, deterministic)
            if backward:
                render.square().mean().backward()
        return render.detach()
    return run


def interleaved_times(fns: dict[str, callable], device: str, repeats: int, warmup: int = 2) -> dict[str, list[float]]:
    """Seconds per run of every closure, the closures taking turns in each repetition."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    now = synced_clock(device)
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = now()
            fn()
            times[name].append(now() - t0)
    return times


def peak_mib(fn, device: str) -> float | None:
    """torch's allocator peak above what was allocated before, in MiB, of one run (CUDA only)."""
    if not device.startswith("cuda"):
        return None
    synchronize(device)
    torch.cuda.empty_cache()
    before = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    fn()
    synchronize(device)
    return (torch.cuda.max_memory_allocated() - before) / 2**20


def _cell(ts: list[float] | None) -> str:
    if not ts:
        return "n/a"
    ms = [t * 1e3 for t in ts]
    return f"{statistics.median(ms):.2f} ({min(ms):.2f}-{max(ms):.2f})"


def _mib(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.0f}"


def batch_table(args: argparse.Namespace, gs) -> list[str]:
    """The markdown lines of the model-workload comparison."""
    device, side, n_scenes = args.device, args.batch_side, args.batch_scenes
    data = workload(n_scenes, side, device)
    impls = {"ours batched": (rasterization, False, False), "ours looped": (rasterization, True, False),
             "ours batched, deterministic": (rasterization, False, True)}
    if gs is not None:
        impls |= {"gsplat batched": (gs, False, False), "gsplat looped": (gs, True, False)}
    rows: dict[str, dict] = {name: {} for name in impls}
    for backward in (False, True):
        fns = {name: render_fn(impl, data, side, looped, backward, det) for name, (impl, looped, det) in impls.items()}
        times = interleaved_times(fns, device, args.repeats)
        for name, fn in fns.items():
            rows[name][backward] = (times[name], peak_mib(fn, device))
    base = "gsplat batched" if gs is not None else "ours looped"
    n = data["means"].shape[1]
    lines = [f"Model workload: {n_scenes} scenes x {TARGETS} targets at {side}x{side}, {n:,} Gaussians per scene "
             f"(SH degree {SH_DEGREE}, antialiased); ms per batch, median (min-max) of {args.repeats} interleaved "
             f"runs; peak = torch allocator peak above the inputs.", "",
             f"| implementation | forward ms | fwd+bwd ms | forward / {base} | fwd+bwd / {base} | "
             "forward peak MiB | fwd+bwd peak MiB |", "|---|---|---|---|---|---|---|"]
    med = {name: {b: statistics.median(r[b][0]) for b in r} for name, r in rows.items()}
    for name, r in rows.items():
        lines.append(f"| {name} | {_cell(r[False][0])} | {_cell(r[True][0])} | "
                     f"{med[name][False] / med[base][False]:.2f} | {med[name][True] / med[base][True]:.2f} | "
                     f"{_mib(r[False][1])} | {_mib(r[True][1])} |")
    # Agreement: the batched call against the loop (bit-identical on the CPU) and against gsplat.
    with torch.no_grad():
        ours = render_fn(rasterization, data, side, False, False)()
        looped = render_fn(rasterization, data, side, True, False)()
        agree = [f"max |ours batched - ours looped| = {float((ours - looped).abs().max()):.3g}"]
        if gs is not None:
            theirs = render_fn(gs, data, side, False, False)()
            mse = float(((ours.double() - theirs.double()) ** 2).mean())
            agree.append(f"PSNR ours vs gsplat (batched) = {math.inf if mse == 0 else -10 * math.log10(mse):.1f} dB")
    lines += ["", "; ".join(agree) + "."]
    return lines
