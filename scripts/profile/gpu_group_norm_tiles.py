"""What the fused GroupNorm (+ GELU) kernels cost with each tile and warp count (the choice behind
``sgmodel.kernels.group_norm.FORWARD_LAUNCH``, ``BACKWARD_LAUNCH`` and ``SUMS_ITERS``). The GroupNorm calls of one
training forward of the paper's model (256 x 256 pairs, batch 32, bf16 autocast, the encoder run once to record
them) are replayed alone, forward (statistics, combine, apply) and backward (sums, dx), for every (tile elements,
warps) pair and, for the backward, every count of tiles a program of its sums walks; the times are summed over the
calls as a step has them. Prints a markdown table (medians of CUDA-event times of the whole set of calls, ms).

    python scripts/profile/gpu_group_norm_tiles.py [--tiles 2048,4096,8192,16384] [--warps 2,4,8] [--batch-size 32]
        [--iters 1,4,8,16] [--repeats 15] [--out FILE]
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import torch
from gpu_conv_channels import median_ms

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from sgmodel.bench.train import synthetic_batch  # noqa: E402
from sgmodel.config import ModelParams  # noqa: E402
from sgmodel.data.loader import to_device  # noqa: E402
from sgmodel.kernels import group_norm  # noqa: E402
from sgmodel.model.layers import amp_autocast  # noqa: E402
from sgmodel.model.network import create_model  # noqa: E402

#: the choices timed by default: tile elements, warps a program
TILES, WARPS, ITERS = "2048,4096,8192,16384", "2,4,8", "1,4,8,16"


def recorded_calls(batch_size: int) -> collections.Counter:
    """(x's shape, dtype, groups, gelu, parts) of each GroupNorm kernel call of one forward, with its count."""
    calls: collections.Counter = collections.Counter()
    forward = group_norm.forward

    def record(x, groups, weight, bias, eps, gelu, parts=1):
        calls[(tuple(x.shape), x.dtype, groups, gelu, parts)] += 1
        return forward(x, groups, weight, bias, eps, gelu, parts)

    device = torch.device("cuda")
    model = create_model(ModelParams(resolution=256), device)
    batch = to_device(synthetic_batch(batch_size, 4, 256), device)
    group_norm.forward = record
    try:
        with torch.no_grad(), amp_autocast(batch["left"]):
            model(batch["left"], batch["right"], batch["K"], batch["baseline"])
    finally:
        group_norm.forward = forward
    del model
    torch.cuda.empty_cache()
    return calls


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tiles", default=TILES, help="tile elements (pixels x channels), comma-separated")
    ap.add_argument("--warps", default=WARPS, help="warps a program, comma-separated")
    ap.add_argument("--iters", default=ITERS, help="tiles a program of the backward's sums walks, comma-separated")
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    calls = recorded_calls(args.batch_size)
    g = torch.Generator(device="cuda").manual_seed(0)
    cases = []
    for (shape, dtype, groups, gelu, parts), count in calls.items():
        x = torch.randn(shape, device="cuda", dtype=dtype, generator=g).contiguous(memory_format=torch.channels_last)
        C = shape[1]
        w = torch.randn(C, device="cuda", generator=g)
        b = torch.randn(C, device="cuda", generator=g)
        dys = [torch.randn(shape[0], C // parts, *shape[2:], device="cuda", dtype=dtype, generator=g)
               .contiguous(memory_format=torch.channels_last) for _ in range(parts)]
        cases.append((count, x, w, b, groups, gelu, parts, dys))
    default = (group_norm.FORWARD_LAUNCH, group_norm.BACKWARD_LAUNCH, group_norm.SUMS_ITERS)

    def forward_all():
        for count, x, w, b, groups, gelu, parts, _ in cases:
            for _ in range(count):
                group_norm.forward(x, groups, w, b, 1e-5, gelu, parts)

    def backward_all():
        for count, x, w, b, groups, gelu, parts, dys in cases:
            mean, rstd = saved[id(x)]
            for _ in range(count):
                group_norm.backward(dys, x, mean, rstd, groups, w, b, gelu, True)

    saved = {id(x): group_norm.forward(x, groups, w, b, 1e-5, gelu, parts)[1:]
             for _, x, w, b, groups, gelu, parts, _ in cases}
    rows = []
    try:
        for tile in (int(t) for t in args.tiles.split(",")):
            for warps in (int(w) for w in args.warps.split(",")):
                group_norm.FORWARD_LAUNCH = group_norm.BACKWARD_LAUNCH = (tile, warps)
                forward_all()  # compiled for this launch
                f = median_ms(forward_all, args.repeats)
                for iters in (int(i) for i in args.iters.split(",")):
                    group_norm.SUMS_ITERS = iters
                    backward_all()
                    rows.append((tile, warps, iters, f, median_ms(backward_all, args.repeats)))
    finally:
        group_norm.FORWARD_LAUNCH, group_norm.BACKWARD_LAUNCH, group_norm.SUMS_ITERS = default
    best_f, best_b = min(rows, key=lambda r: r[3]), min(rows, key=lambda r: r[4])
    lines = [f"# GroupNorm (+ GELU) kernels by tile and warps, on {torch.cuda.get_device_name()}", "",
             f"{sum(calls.values())} calls a forward ({len(calls)} shapes: " +
             "; ".join(f"{n} x {list(s)} {str(d).removeprefix('torch.')} G{gr}{' GELU' if ge else ''}"
                       f"{f' {p} parts' if p > 1 else ''}" for (s, d, gr, ge, p), n in calls.items()) +
             f"); batch {args.batch_size}; medians of {args.repeats}, ms a step. The code's choice: forward "
             f"{default[0]}, backward {default[1]}, its sums over {default[2]} tiles a program.", "",
             "| tile elements | warps | forward | sums: tiles a program | backward |", "|---:|---:|---:|---:|---:|"]
    for tile, warps, iters, f, b in rows:
        mark_f = "**" if (tile, warps) == best_f[:2] else ""
        mark_b = "**" if (tile, warps, iters) == best_b[:3] else ""
        lines.append(f"| {tile} | {warps} | {mark_f}{f:.2f}{mark_f} | {iters} | {mark_b}{b:.2f}{mark_b} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
