"""Where a training step's GPU time goes: ``torch.profiler`` over steps run back to back as ``sgmodel train`` runs
them (each batch checked on the host and copied from page-locked memory, each step's values read once the next is
queued) at the paper's size (synthetic batches, as ``sgmodel bench train``; the LPIPS term's VGG16 compiled, as
``sgmodel train`` runs it on CUDA). Prints markdown: the top CUDA kernels per step, their
time by kind, and the GPU's idle gaps (first kernel to last) with the host operation that was running when
each of the largest began; then the PyTorch operations with the most GPU time of their own, by input shape
(which elementwise kernel, copy or reduction comes from where). Used by scripts/gpu/train_step.sh
(profile). ``--cached-encoder``: the encoder's outputs given with the batch, as ``--encoder-cache`` gives them.
Last, the host synchronisations of one more step queued, each with where our code called it (torch's sync debug mode:
PyTorch's own operations only; Warp's, the binning's read of its sizes, are not seen there).

    python scripts/profile/gpu_train_profile.py [--steps 3] [--lpips-random-vgg] [--cached-encoder] [--top 40] [--out FILE]
"""

from __future__ import annotations

import argparse
import bisect
import collections
import sys
import time
import traceback
import warnings
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from sgmodel.bench.train import synthetic_batch  # noqa: E402
from sgmodel.config import ModelParams  # noqa: E402
from sgmodel.data.loader import map_tensors, to_device  # noqa: E402
from sgmodel.metrics.lpips import random_lpips  # noqa: E402
from sgmodel.model.layers import amp_autocast, compiles  # noqa: E402
from sgmodel.model.network import create_model, encode_pair  # noqa: E402
from sgmodel.train.step import create_optimizer, device_batch, queue_step, steps_back_to_back  # noqa: E402
from sgmodel.train.losses import Objective  # noqa: E402

#: kernel kinds, first match of a name fragment wins.
KINDS = (("convolution (cuDNN)", ("xmma", "cutlass", "implicit_gemm", "conv2d_c1_k1", "sm90_", "sm80_")),
         ("cuDNN layout conversion", ("nchwToNhwc", "nhwcToNchw")),
         ("rasteriser (Warp)", ("cuda_kernel_forward",)),
         ("GroupNorm + GELU (Triton)", ("_stats_kernel", "_apply_kernel", "_backward_sums_kernel",
                                        "_backward_dx_kernel")),
         ("bilinear upsampling (Triton)", ("_upsample_forward_kernel", "_upsample_backward_kernel")),
         ("SSIM term (Triton)", ("_ssim_forward_kernel", "_ssim_backward_kernel")),
         ("bias + GELU (Triton)", ("_bias_gelu_forward_kernel", "_bias_gelu_backward_kernel")),
         ("GroupNorm (PyTorch)", ("RowwiseMoments", "ComputeFusedParams", "GroupNorm", "ComputeInternalGradients",
                                  "Compute1dBackward", "ComputeBackwardFused", "GammaBeta")),
         ("GELU", ("Gelu",)),
         ("batch norm (encoder)", ("batch_norm",)),
         ("depthwise convolution (SSIM)", ("conv_depthwise",)),
         ("copies, concatenations, padding", ("copy", "Copy", "CatArray", "replication", "Memset", "fill")),
         ("other elementwise and reductions", ("elementwise", "reduce", "Reduce")))


def kind(name: str) -> str:
    return next((k for k, keys in KINDS if any(s in name for s in keys)), "other")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3, help="profiled steps (after 3 warm-up steps)")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--lpips-random-vgg", action="store_true", help="the LPIPS term on random VGG16 weights")
    ap.add_argument("--cached-encoder", action="store_true", help="the encoder's outputs come with the batch")
    ap.add_argument("--top", type=int, default=40, help="kernels (and operations) listed")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    device = torch.device("cuda")
    torch.backends.cudnn.benchmark = True
    model = create_model(ModelParams(resolution=args.resolution), device)
    lpips = random_lpips(device) if args.lpips_random_vgg else None
    if compiles(device):  # the LPIPS term's VGG16 compiled, as `sgmodel train` runs it
        lpips = lpips and lpips.compile_trunk()
    objective = Objective(lpips, reason="profiled", amp=True)
    optimizer = create_optimizer([p for p in model.parameters() if p.requires_grad], device, lr=1e-5)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
    hosts = [synthetic_batch(args.batch_size, 4, args.resolution, i) for i in range(2)]
    for host in hosts if args.cached_encoder else []:
        batch = to_device(host, device)
        with amp_autocast(batch["left"]):
            disparity, features = encode_pair(model.encoder, batch["left"], batch["right"])
        host["encoder_disparity"], host["encoder_features"] = disparity.cpu(), [f.to(torch.bfloat16).cpu()
                                                                              for f in features]
    hosts = [map_tensors(h, torch.Tensor.pin_memory) for h in hosts]  # as the loader's batches on CUDA

    def queue(i: int):
        return queue_step(model, device_batch(hosts[i % 2], device), objective, optimizer, scheduler, True)

    steps_back_to_back(queue, 3)
    torch.cuda.synchronize()
    n = args.steps
    t0 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA], record_shapes=True) as prof:
        steps_back_to_back(queue, n)
        torch.cuda.synchronize()
    wall = (time.perf_counter() - t0) * 1e3 / n
    events = prof.events()
    kernels = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
    per_name: dict[str, list[float]] = {}
    for e in kernels:
        entry = per_name.setdefault(e.name, [0.0, 0])
        entry[0] += (e.time_range.end - e.time_range.start) / 1e3 / n
        entry[1] += 1 / n
    busy_total = sum(v[0] for v in per_name.values())
    lines = [f"# Training step profile: {args.resolution}x{args.resolution}, batch {args.batch_size}, 4 targets, "
             f"psmnet-kitti{' (outputs given)' if args.cached_encoder else ''}, bf16, loss {objective.name}, on "
             f"{torch.cuda.get_device_name()}",
             "", f"{n} profiled steps; {wall:.1f} ms a step with the profiler on; kernels {busy_total:.1f} ms a step "
             f"({len(kernels) / n:.0f} launches a step).", "", "| kernel | ms / step | launches / step | share |",
             "|---|---:|---:|---:|"]
    for name, (ms, calls) in sorted(per_name.items(), key=lambda kv: -kv[1][0])[:args.top]:
        lines.append(f"| `{name[:100]}` | {ms:.2f} | {calls:.0f} | {100 * ms / busy_total:.1f}% |")
    by_kind: dict[str, float] = {}
    for name, (ms, _) in per_name.items():
        by_kind[kind(name)] = by_kind.get(kind(name), 0.0) + ms
    lines += ["", "| kind (by kernel name) | ms / step | share |", "|---|---:|---:|"]
    lines += [f"| {k} | {ms:.1f} | {100 * ms / busy_total:.0f}% |"
              for k, ms in sorted(by_kind.items(), key=lambda kv: -kv[1])]
    lines += [""] + gaps(kernels, [e for e in events if e.device_type == torch.autograd.DeviceType.CPU], n)
    ops = sorted(prof.key_averages(group_by_input_shape=True), key=lambda e: -e.self_device_time_total)
    lines += ["", "| operation | input shapes | self GPU ms / step | calls / step |", "|---|---|---:|---:|"]
    lines += [f"| `{e.key[:100]}` | `{str(e.input_shapes)[:90]}` | {e.self_device_time_total / 1e3 / n:.2f} | "
              f"{e.count / n:.0f} |" for e in ops[:args.top]]
    lines += [""] + host_syncs(lambda: queue(0))
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


def gaps(kernels, host_ops, n: int) -> list[str]:
    """The GPU's idle time between its first and last kernel, and the largest gaps with the host operations
    that were running when each began (the host was busy issuing them while the GPU waited)."""
    spans = sorted((e.time_range.start, e.time_range.end) for e in kernels)
    busy, idle = 0.0, []
    start, end = spans[0]
    for s, e in spans[1:]:
        if s > end:
            busy += end - start
            idle.append((s - end, end))
            start, end = s, e
        else:
            end = max(end, e)
    busy += end - start
    span = spans[-1][1] - spans[0][0]
    host_ops = sorted(host_ops, key=lambda e: e.time_range.start)
    starts = [e.time_range.start for e in host_ops]
    out = [f"GPU busy {busy / 1e3 / n:.1f} of {span / 1e3 / n:.1f} ms a step (first kernel to last): idle "
           f"{(span - busy) / 1e3 / n:.1f} ms in {len(idle) / n:.0f} gaps a step, "
           f"{sum(g for g, _ in idle if g > 100) / 1e3 / n:.1f} ms of it in gaps over 100 us. Largest gaps:", ""]
    for g, t in sorted(idle, reverse=True)[:12]:
        j, names = bisect.bisect_right(starts, t) - 1, []
        while j >= 0 and len(names) < 3:
            if host_ops[j].time_range.end >= t:
                names.append(host_ops[j].name[:50])
            j -= 1
        out.append(f"- {g:.0f} us, host in: {', '.join(reversed(names))}")
    return out


def host_syncs(step) -> list[str]:
    """Each PyTorch operation of ``step()`` that waits for the GPU, by where our code called it (its three
    innermost frames in sgmodel or scenesplat_stereo), with its count."""
    seen: collections.Counter = collections.Counter()

    def note(message, *_):
        ours = [f for f in traceback.extract_stack()[:-1]
                if "/sgmodel/" in f.filename or "/scenesplat_stereo/" in f.filename]
        where = " <- ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in reversed(ours[-3:]))
        seen[(str(message).splitlines()[0][:70], where or "outside our code")] += 1

    torch.cuda.synchronize()
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = note
        torch.cuda.set_sync_debug_mode("warn")
        try:
            step()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    rows = [f"| {n} | {what} | {where} |" for (what, where), n in seen.most_common()]
    return [f"Host synchronisations in one step (torch's sync debug mode): {sum(seen.values())}", "",
            "| count | operation | called from |", "|---:|---|---|", *rows]


if __name__ == "__main__":
    sys.exit(main())
