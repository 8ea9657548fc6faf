"""``sgmodel bench train``: one training step split by stage, with the SSIM and the LPIPS term, and its peak memory.

Stages (each synchronised on CUDA, so the split is honest and the sum is a little above a free-running step):
data (the next batch from the loader, when ``--data`` is given; else a synthetic batch and no data time),
encoder, decoder + predictor, composer, rasterisation forward, loss, backward, optimiser. Then the free-running
``train_step`` on the same batch on the device (no synchronisation inside, one before and after). Medians of
``--repeats`` steps after ``--warmup``. Then the step time a run sees: steps back to back as ``sgmodel train``
runs them (each with the loader's next batch when ``--data`` is given, else two synthetic batches in turn; each
batch checked on the host and copied, each step's values read once the next is queued), the mean step of a round
of ``--repeats``, the median of three rounds after one untimed. Peak memory is
``torch.cuda.max_memory_allocated`` over each objective's steps. The step is timed with MSE + 0.05 (1 - SSIM)
and, when VGG16 weights are given (``--lpips-vgg FILE``) or random ones are asked for (``--lpips-random-vgg``:
the time does not depend on the weights' values; for machines without the ImageNet file), again with MSE + 0.05
LPIPS-VGG.

The decoder + predictor's FLOPs are counted by ``torch.utils.flop_counter`` (convolutions and matrix
products, forward and backward) and divided by their forward stage time and by the time of their forward
and backward alone, as a fraction of the GPU's dense bf16 rate: the spec sheet's (989.4 TFLOP/s for the
H100 SXM and the H200) and the rate of one 8192^3 bf16 matrix product measured here.
Defaults are the paper's step: 256x256, batch 32, 4 targets, psmnet-kitti.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from scenesplat_stereo.common.measure import synced_clock
from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import markdown_table
from sgmodel.args import add_device_argument, add_model_arguments, device_from_flag, params_from_args
from sgmodel.bench import report
from sgmodel.data.encoder_cache import open_cache, precision_of
from sgmodel.data.loader import make_loader
from sgmodel.metrics.lpips import random_lpips, vgg16_missing_message
from sgmodel.model.geometry import depth_from_disparity
from sgmodel.model.layers import amp_autocast, compiles
from sgmodel.model.network import create_model
from sgmodel.model.render import render_views
from sgmodel.train.step import (cached_encoding, create_optimizer, device_batch, queue_step, steps_back_to_back,
                                train_step)
from sgmodel.train.losses import Objective, create_objective

OWNER = "sgmodel bench train"  # recorded beside --out: a later run may replace its own report
STAGES = ("data", "encoder", "decoder + predictor", "composer", "rasterisation forward", "loss", "backward",
          "optimiser")
#: dense bf16 tensor-core rate on the spec sheet, TFLOP/s, by a name fragment of the GPU.
BF16_SPEC_TFLOPS = {"H100": 989.4, "H200": 989.4}
#: rounds of ``--repeats`` back-to-back steps timed (their median is reported), after one untimed
BACK_TO_BACK_ROUNDS = 3


def synthetic_batch(batch: int, targets: int, size: int, seed: int = 0) -> dict:
    """A batch on the host with the shapes of real data: smooth random images, a plausible K and baseline,
    targets within 0.3 m of the reference camera."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(batch, 3, size // 16, size // 16, generator=g)
    left = torch.nn.functional.interpolate(low, size=(size, size), mode="bicubic", align_corners=False).clamp(0, 1)
    right = torch.roll(left, shifts=-4, dims=-1)
    K = torch.tensor([[size * 0.9, 0, size / 2], [0, size * 0.9, size / 2], [0, 0, 1]]).expand(batch, 3, 3).clone()
    view = torch.eye(4).expand(batch, targets, 4, 4).clone()
    view[..., :3, 3] = (torch.rand(batch, targets, 3, generator=g) - 0.5) * 0.3
    return {"left": left, "right": right, "K": K, "baseline": torch.full((batch,), 0.1),
            "targets": left[:, None].expand(batch, targets, 3, size, size).clone(),
            "masks": torch.ones(batch, targets, 1, size, size, dtype=torch.bool),
            "target_viewmats": view, "target_Ks": K[:, None].expand(batch, targets, 3, 3).clone(),
            "keys": [f"synthetic_{i}" for i in range(batch)]}


def _encoded(model, batch: dict, amp: bool):
    """(depth z, features) of the batch's pairs: the encoder's, or the encoder cache's when the batch has them."""
    cached = cached_encoding(batch)
    with amp_autocast(batch["left"], amp):
        disparity, features = model.encode(batch["left"], batch["right"]) if cached is None else cached
    return depth_from_disparity(disparity, batch["K"][:, 0, 0], batch["baseline"]), features


def staged_step(model, objective, optimizer, batch: dict, amp: bool, now) -> dict[str, float]:
    """One training step through the model's stage methods, timing each (seconds)."""
    t0 = now()
    optimizer.zero_grad(set_to_none=True)
    z, features = _encoded(model, batch, amp)
    t1 = now()
    with amp_autocast(batch["left"], amp):
        front, back, dz, c = model.layers(batch["left"], z, features, batch["K"])
    t2 = now()
    gaussians = model.compose(front, back, dz, c, batch["baseline"])
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
    return {"encoder": t1 - t0, "decoder + predictor": t2 - t1, "composer": t3 - t2, "rasterisation forward": t4 - t3,
            "loss": t5 - t4, "backward": t6 - t5, "optimiser": t7 - t6}


def _layer_outputs(model, batch: dict, encoded, amp: bool) -> list[torch.Tensor]:
    """The decoder + predictor's outputs (front, back, dz; those the model has) from ``encoded`` (z, features)."""
    z, features = encoded
    with amp_autocast(batch["left"], amp):
        return [o for o in model.layers(batch["left"], z, features, batch["K"])[:3] if o is not None]


def _backward_from_ones(outputs: list[torch.Tensor]) -> None:
    torch.autograd.backward(outputs, [torch.ones_like(o) for o in outputs])


def layer_flops(model, batch: dict, amp: bool, encoded=None) -> tuple[float, float]:
    """(forward, forward + backward) FLOPs of the decoder + predictor on ``batch`` (``encoded``: its
    ``_encoded`` outputs, computed here when not given)."""
    encoded = _encoded(model, batch, amp) if encoded is None else encoded
    with FlopCounterMode(display=False) as forward:
        outputs = _layer_outputs(model, batch, encoded, amp)
    with FlopCounterMode(display=False) as backward:
        _backward_from_ones(outputs)
    model.zero_grad(set_to_none=True)
    return float(forward.get_total_flops()), float(forward.get_total_flops() + backward.get_total_flops())


def matmul_tflops(device: torch.device, n: int = 8192, repeats: int = 10) -> float:
    """The rate of an n^3 bf16 matrix product on ``device`` (TFLOP/s), median of ``repeats`` after 3."""
    a, b = (torch.randn(n, n, device=device, dtype=torch.bfloat16) for _ in range(2))
    now = synced_clock(device)
    times = []
    for i in range(repeats + 3):
        t0 = now()
        a @ b
        if i >= 3:
            times.append(now() - t0)
    return 2 * n**3 / statistics.median(times) / 1e12


def measure(model, objective: Objective, batches, args, device: torch.device, amp: bool) -> dict:
    """Stage medians (ms), the free-running step (ms), the back-to-back step (ms) and the peak memory (MiB) of one
    objective. ``batches(i)``: (host batch i, seconds the loader took for it)."""
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = create_optimizer(params, device, lr=1e-5)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
    now = synced_clock(device)
    stages: dict[str, list[float]] = {s: [] for s in STAGES}
    free: list[float] = []
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
    first = 0.0
    hosts = []
    for i in range(args.warmup + args.repeats):
        host, data_s = batches(i)
        hosts = [*hosts[-1:], host]
        batch = device_batch(host, device)
        t_first = now()
        split = staged_step(model, objective, optimizer, batch, amp, now)
        if i == 0:
            first = now() - t_first
        t0 = now()
        train_step(model, batch, objective, optimizer, scheduler, amp)
        step_s = now() - t0
        if i >= args.warmup:
            stages["data"].append(data_s)
            for k, v in split.items():
                stages[k].append(v)
            free.append(step_s)
    rounds = []
    for r in range(BACK_TO_BACK_ROUNDS + 1):  # the first round warms up
        t0 = now()
        steps_back_to_back(lambda i: queue_step(model, device_batch(batches(i)[0] if args.data else
                                                                    hosts[i % len(hosts)], device),
                                                objective, optimizer, scheduler, amp), args.repeats)
        if r:
            rounds.append((now() - t0) / args.repeats)
    back_to_back = statistics.median(rounds)
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else float("nan")
    return {"stages": {k: statistics.median(v) * 1e3 for k, v in stages.items()},
            "step": statistics.median(free) * 1e3, "back_to_back": back_to_back * 1e3, "peak": peak, "first": first}


def run(args: argparse.Namespace) -> int:
    model_params, _ = params_from_args(args)
    out = OwnedFile(args.out, "--out", OWNER)  # before any work
    device = torch.device(device_from_flag(args.device))
    torch.backends.cudnn.benchmark = device.type == "cuda"  # as `sgmodel train` does
    model = create_model(model_params, device)
    S, amp = model_params.resolution, not args.no_amp
    compiled = compiles(device, not args.no_compile_lpips)  # as `sgmodel train` does
    objectives = [Objective(None, reason="the bench times both" if args.lpips_vgg or args.lpips_random_vgg
                            else vgg16_missing_message(), amp=amp)]
    if args.lpips_random_vgg:
        net = random_lpips(device)
        objectives.append(Objective(net.compile_trunk() if compiled else net, amp=amp))
    elif args.lpips_vgg:
        objectives.append(create_objective(args.lpips_vgg, device=device, amp=amp, compile_trunk=compiled))
    if args.encoder_cache is not None and args.data is None:
        raise ValueError("--encoder-cache: give the --data it caches")
    cache = open_cache(args.encoder_cache, args.data, model.encoder, S, precision_of(device, amp), ["train"]) \
        if args.encoder_cache is not None else None
    loader = iter(make_loader(args.data, "train", args.batch_size, S, args.targets, 0, args.workers, 0, 1,
                              train=True, cache=cache, pin_memory=device.type == "cuda")) if args.data else None

    def batches(i: int) -> tuple[dict, float]:
        if loader is None:
            return synthetic_batch(args.batch_size, args.targets, S, i), float("nan")
        t0 = time.perf_counter()
        batch = next(loader)
        return batch, time.perf_counter() - t0

    results = [measure(model, objective, batches, args, device, amp) for objective in objectives]
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    header = ["stage"] + [f"{o.name}, median ms" for o in objectives]
    rows = [[k] + [f"{r['stages'][k]:.1f}" if r["stages"][k] == r["stages"][k] else "n/a" for r in results]
            for k in STAGES]
    rows += [["**sum of stages (synchronised)**"] + [f"{sum(v for v in r['stages'].values() if v == v):.1f}"
                                                     for r in results],
             ["**free-running step** (`train_step`, data excluded)"] + [f"**{r['step']:.1f}**" for r in results],
             ["**back-to-back steps** (as `sgmodel train` runs them, the loader's batch each step with `--data`)"]
             + [f"**{r['back_to_back']:.1f}**" for r in results],
             ["peak memory, MiB"] + [f"{r['peak']:.0f}" for r in results],
             ["first step, s (cuDNN's algorithm search; compilation)"] + [f"{r['first']:.1f}" for r in results]]
    gaussians = (2 if model_params.composer.back_layer else 1) * (S + 2 * model_params.padding) ** 2
    report(f"One training step: {S}x{S}, batch {args.batch_size}, {args.targets} targets, encoder "
           f"{model_params.encoder.name}, {'bf16 autocast' if amp else 'float32'}, on {name}; medians of "
           f"{args.repeats} steps after {args.warmup} warm-up "
           f"({'real shards: ' + str(args.data) if args.data else 'synthetic batches'}"
           f"{'; the encoder outputs read from the cache ' + str(args.encoder_cache) if cache else ''}). Losses: "
           + "; ".join(f"{o.name} = {o.description}" for o in objectives)
           + (f"; the LPIPS term's VGG16 {'through torch.compile' if compiled else 'eager'}" if len(objectives) > 1
              else "") + ".\n\n"
           f"{markdown_table(header, rows)}\n\nGaussians per scene: {gaussians:,}.\n\n"
           + layer_rate(model, device_batch(batches(0)[0], device), amp, device,
                        results[0]["stages"]["decoder + predictor"], args.repeats),
           out)
    return 0


def layer_rate(model, batch: dict, amp: bool, device: torch.device, forward_ms: float, repeats: int) -> str:
    """The decoder + predictor's FLOPs and their rate, forward (its stage) and forward + backward alone."""
    encoded = _encoded(model, batch, amp)
    forward, total = layer_flops(model, batch, amp, encoded)
    now = synced_clock(device)
    times = []
    for i in range(repeats + 2):
        t0 = now()
        _backward_from_ones(_layer_outputs(model, batch, encoded, amp))
        if i >= 2:
            times.append(now() - t0)
        model.zero_grad(set_to_none=True)
    both_ms = statistics.median(times) * 1e3
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else ""
    spec = next((v for k, v in BF16_SPEC_TFLOPS.items() if k in name), None)
    measured = matmul_tflops(device) if device.type == "cuda" else None
    rows = []
    for what, flops, ms in (("forward (the stage above)", forward, forward_ms),
                            ("forward + backward, alone", total, both_ms)):
        rate = flops / ms / 1e9
        rows.append([what, f"{flops / 1e12:.2f}", f"{ms:.1f}", f"{rate:.0f}",
                     f"{100 * rate / spec:.0f}%" if spec else "n/a",
                     f"{100 * rate / measured:.0f}%" if measured else "n/a"])
    table = markdown_table(["decoder + predictor", "TFLOP", "ms", "TFLOP/s", "of the bf16 spec",
                            "of a measured 8192^3 bf16 matmul"], rows)
    return (f"{table}\n\nbf16 rates: spec sheet {spec or 'n/a'} TFLOP/s (dense); an 8192^3 bf16 matrix product "
            f"measured {measured:.0f} TFLOP/s here.\n" if measured else f"{table}\n")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    add_device_argument(p)
    p.add_argument("--data", type=Path, help="time real batches from this dataset (default: synthetic batches)")
    p.add_argument("--batch-size", type=int, default=32, help="pairs per step (default 32)")
    p.add_argument("--targets", type=int, default=4, help="targets per pair (default 4)")
    p.add_argument("--workers", type=int, default=8, help="DataLoader workers with --data (default 8)")
    p.add_argument("--encoder-cache", type=Path, metavar="CACHE",
                   help="with --data: read the encoder's outputs from this cache (`sgmodel encode`), as `sgmodel "
                        "train --encoder-cache` does (the encoder stage is then the depth from the disparity)")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps first (default 3)")
    p.add_argument("--repeats", type=int, default=10, help="timed steps (default 10)")
    lpips = p.add_mutually_exclusive_group()
    lpips.add_argument("--lpips-vgg", help="VGG16 weights (torchvision's file): also time the step with LPIPS-VGG")
    lpips.add_argument("--lpips-random-vgg", action="store_true",
                       help="also time the step with LPIPS-VGG on randomly initialised VGG16 weights (timing only: "
                            "the time does not depend on the weights)")
    p.add_argument("--no-amp", action="store_true", help="float32 convolutions")
    p.add_argument("--no-compile-lpips", action="store_true",
                   help="the LPIPS term's VGG16 eagerly (default on CUDA: torch.compile, as sgmodel train)")
    p.add_argument("--out", type=Path, help="also write the markdown table here (a report of an earlier run of this "
                   "bench is replaced, any other file refused)")
