"""What the predictor's 3x3 convolutions cost with their channel counts padded to 8, 16, 32 or 64 (the
choice behind ``sgmodel.model.layers.CUDA_INPUT_MULTIPLE`` and ``CUDA_OUTPUT_MULTIPLE``): cuDNN's forward,
and its backward (input and weight gradients), of each convolution of the predictor at the paper's training
size, bf16, channels-last, with cuDNN's algorithm search on as training runs it. Zero channels change no
result, only the kernels cuDNN picks and the work they do. Prints a markdown table (medians of CUDA-event
times, ms).

    python scripts/profile/gpu_conv_channels.py [--batch-size 32] [--size 288] [--repeats 20] [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from sgmodel.model.layers import round_up  # noqa: E402

#: (the convolution, input channels, output channels) as the predictor has them (256 x 256 pairs, canvas 288).
CONVS = (("the branches' first layers, stacked", 128 + 3 + 128, 3 * 128),
         ("the regressor's first layer", 3 + 1 + 128, 128),
         ("a front or back layer's final conv", 128, 37),
         ("the dz branch's final conv", 128, 1))
MULTIPLES = (8, 16, 32, 64)


def median_ms(fn, repeats: int) -> float:
    """Median of ``repeats`` times of ``fn()`` between CUDA events recorded around it (the stream's time), ms."""
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        torch.cuda.synchronize()
        times.append(start.elapsed_time(end))
    return sorted(times)[len(times) // 2]


def time_conv(cin: int, cout: int, batch: int, size: int, repeats: int) -> tuple[float, float]:
    """(forward ms, backward ms) of a 3x3 convolution [batch, cin, size, size] -> cout, bf16 channels-last."""
    fmt = torch.channels_last
    x = torch.randn(batch, cin, size, size, device="cuda", dtype=torch.bfloat16).to(memory_format=fmt)
    w = (torch.randn(cout, cin, 3, 3, device="cuda", dtype=torch.bfloat16) * 0.05).to(memory_format=fmt)
    x.requires_grad_(True)
    w.requires_grad_(True)
    dy = torch.randn(batch, cout, size, size, device="cuda", dtype=torch.bfloat16).to(memory_format=fmt)
    for _ in range(3):  # cuDNN's search, then warm
        y = F.conv2d(x, w, padding=1)
        y.backward(dy)
    forward = median_ms(lambda: F.conv2d(x, w, padding=1), repeats)

    def step() -> None:
        torch.autograd.grad(F.conv2d(x, w, padding=1), (x, w), dy)
    both = median_ms(step, repeats)
    return forward, both - forward


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--size", type=int, default=288, help="canvas side, pixels")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    torch.backends.cudnn.benchmark = True
    title = (f"# 3x3 convolutions with padded channels: batch {args.batch_size}, {args.size}x{args.size}, bf16, "
             f"channels-last, on {torch.cuda.get_device_name()} (torch {torch.__version__}, cuDNN "
             f"{torch.backends.cudnn.version()}); medians of {args.repeats}, ms")
    lines = [title, "",
             "| convolution | multiple | channels in -> out | forward | backward | sum |", "|---|---:|---|---:|---:|---:|"]
    for name, cin, cout in CONVS:
        seen = set()
        for m in MULTIPLES:
            shape = (round_up(cin, m), round_up(cout, m))
            if shape in seen:
                continue
            seen.add(shape)
            fwd, bwd = time_conv(*shape, args.batch_size, args.size, args.repeats)
            lines.append(f"| {name} | {m} | {shape[0]} -> {shape[1]} | {fwd:.2f} | {bwd:.2f} | {fwd + bwd:.2f} |")
            print(lines[-1], flush=True)
            torch.cuda.empty_cache()
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
