"""``sgmodel bench train``: one training step split by stage, and its peak memory.

Stages (each synchronised on CUDA, so the split is honest and the sum is a little above a free-running
step): data (the next batch from the loader, when ``--data`` is given; else a synthetic batch and no data
time), encoder, decoder + predictor, composer, rasterisation forward, loss, backward, optimiser. Then the
free-running ``train_step`` (no synchronisation inside) as the step time a run sees. Medians of
``--repeats`` steps after ``--warmup``; peak memory is ``torch.cuda.max_memory_allocated``.
Defaults are the paper's step: 256x256, batch 32, 4 targets, psmnet-kitti.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch

from scenesplat_stereo.text import markdown_table

from ..args import add_model_arguments, params_from_args
from ..data import make_loader
from ..geometry import depth_from_disparity
from ..losses import create_objective
from ..model import create_model
from ..render import render_views
from ..train import to_device, train_step
from . import report, synced_clock

STAGES = ("data", "encoder", "decoder + predictor", "composer", "rasterisation forward", "loss", "backward",
          "optimiser")


def synthetic_batch(batch: int, targets: int, size: int, device: torch.device, seed: int = 0) -> dict:
    """A batch with the shapes of real data: smooth random images, a plausible K and baseline, targets
    within 0.3 m of the reference camera."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(batch, 3, size // 16, size // 16, generator=g)
    left = torch.nn.functional.interpolate(low, size=(size, size), mode="bicubic", align_corners=False).clamp(0, 1)
    right = torch.roll(left, shifts=-4, dims=-1)
    K = torch.tensor([[size * 0.9, 0, size / 2], [0, size * 0.9, size / 2], [0, 0, 1]]).expand(batch, 3, 3).clone()
    view = torch.eye(4).expand(batch, targets, 4, 4).clone()
    view[..., :3, 3] = (torch.rand(batch, targets, 3, generator=g) - 0.5) * 0.3
    return to_device({"left": left, "right": right, "K": K, "baseline": torch.full((batch,), 0.1),
                      "targets": left[:, None].expand(batch, targets, 3, size, size).clone(),
                      "masks": torch.ones(batch, targets, 1, size, size, dtype=torch.bool),
                      "target_viewmats": view, "target_Ks": K[:, None].expand(batch, targets, 3, 3).clone(),
                      "keys": [f"synthetic_{i}" for i in range(batch)]}, device)


def staged_step(model, objective, optimizer, batch: dict, amp: bool, now) -> dict[str, float]:
    """One training step through the model's stage methods, timing each (seconds)."""
    t = {}
    t0 = now()
    left, K, b = batch["left"], batch["K"], batch["baseline"]
    optimizer.zero_grad(set_to_none=True)
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp and left.is_cuda):
        disparity, features = model.encode(left, batch["right"])
        z = depth_from_disparity(disparity, K[:, 0, 0], b)
        t1 = now()
        front, back, dz, c = model.layers(left, z, features, K)
        t2 = now()
    gaussians = model.compose(front, back, dz, c, b)
    t3 = now()
    S = batch["targets"].shape[-1]
    rgb, _ = render_views(gaussians, batch["target_viewmats"], batch["target_Ks"], S, S)
    t4 = now()
    loss, _ = objective(rgb.flatten(0, 1), batch["targets"].flatten(0, 1))
    t5 = now()
    loss.backward()
    t6 = now()
    optimizer.step()
    t7 = now()
    t.update({"encoder": t1 - t0, "decoder + predictor": t2 - t1, "composer": t3 - t2,
              "rasterisation forward": t4 - t3, "loss": t5 - t4, "backward": t6 - t5, "optimiser": t7 - t6})
    return t


def run(args: argparse.Namespace) -> int:
    model_params, train_params = params_from_args(args)
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = device.type == "cuda"  # as `sgmodel train` does
    model = create_model(model_params, device)
    S, amp = model_params.resolution, not args.no_amp
    objective = create_objective(args.lpips_vgg, device=device, amp=amp)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=1e-5)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
    loader = iter(make_loader(args.data, "train", args.batch_size, S, args.targets, 0, args.workers, 0, 1,
                              train=True)) if args.data else None
    now = synced_clock(device)
    stages: dict[str, list[float]] = {s: [] for s in STAGES}
    free: list[float] = []
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    real = loader is not None
    for i in range(args.warmup + args.repeats):
        t0 = now()
        batch = to_device(next(loader), device) if real else synthetic_batch(args.batch_size, args.targets, S, device, i)
        data_s = now() - t0 if real else float("nan")
        split = staged_step(model, objective, optimizer, batch, amp, now)
        t0 = now()
        train_step(model, batch, objective, optimizer, scheduler, amp)
        step_s = now() - t0
        if i >= args.warmup:
            stages["data"].append(data_s)
            for k, v in split.items():
                stages[k].append(v)
            free.append(step_s)
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else float("nan")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    med = {k: statistics.median(v) * 1e3 for k, v in stages.items()}
    total = sum(v for v in med.values() if v == v)
    rows = [[k, f"{med[k]:.1f}", f"{100 * med[k] / total:.0f}%"] if med[k] == med[k] else [k, "n/a", ""]
            for k in STAGES]
    rows += [["**sum of stages (synchronised)**", f"{total:.1f}", ""],
             ["**free-running step** (`train_step`, data excluded)", f"{statistics.median(free) * 1e3:.1f}", ""]]
    gaussians = (2 if model_params.composer.back_layer else 1) * (S + 2 * model_params.padding) ** 2
    report(f"One training step: {S}x{S}, batch {args.batch_size}, {args.targets} targets, encoder "
           f"{model_params.encoder.name}, loss {objective.description}, {'bf16 autocast' if amp else 'float32'}, "
           f"on {name}; medians of {args.repeats} steps after {args.warmup} warm-up "
           f"({'real shards: ' + str(args.data) if args.data else 'synthetic batches'}).\n\n"
           f"{markdown_table(['stage', 'median ms', 'share'], rows)}\n\n"
           f"Peak memory: {peak:.0f} MiB; Gaussians per scene: {gaussians:,}.\n", args.out)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    p.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    p.add_argument("--data", type=Path, help="time real batches from this dataset (default: synthetic batches)")
    p.add_argument("--batch-size", type=int, default=32, help="pairs per step (default 32)")
    p.add_argument("--targets", type=int, default=4, help="targets per pair (default 4)")
    p.add_argument("--workers", type=int, default=8, help="DataLoader workers with --data (default 8)")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps first (default 3)")
    p.add_argument("--repeats", type=int, default=10, help="timed steps (default 10)")
    p.add_argument("--lpips-vgg", help="VGG16 weights for the LPIPS term (default: hub cache, else 1 - SSIM)")
    p.add_argument("--no-amp", action="store_true", help="float32 convolutions")
    p.add_argument("--out", type=Path, help="also write the markdown table here")
