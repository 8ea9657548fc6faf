"""The composer through ``torch.compile`` against the eager composer, on CUDA, at the batch shapes training runs
(issue 34): why the composer runs eager (docs/benchmarks.md "Issue 34, fifth lease"), and the check any return
to a compiled composer has to pass.

    python scripts/checks/compiled_composer.py [--batches 1 4 16 32] [--canvas 288] [--device cuda] [--out FILE]

For each batch size the same random inputs, shaped as the paper model gives them at 256x256 (the predictor's
bf16 front and back branches, dz, a canvas depth with edges, RGB; ``--canvas`` pixels a side) go through
``compose`` eager and compiled (inductor, static shapes, one compilation per batch size, as training had it), and
so does ``back_depth`` alone (the back layer's depth: the 9 x 9 stride-1 max of z~ over a -inf border, plus
softplus(dz)). The report gives, per batch size, the relative L2 distance of every output and of the gradients of
a fixed random projection of them. Eager and compiled computing the same operations differ by float32
rounding (about 1e-7); the fifth lease found centres and scales 2.6-2.8e-2 apart at a batch of 32 on an H100. Set
``TORCHINDUCTOR_DETERMINISTIC=1`` to take inductor's kernel choice by rule instead of by timing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from scenesplat_stereo.common.ownership import OwnedFile  # noqa: E402
from sgmodel.bench import report  # noqa: E402
from sgmodel.model.composer import LAYER_CHANNELS, back_depth, compose  # noqa: E402


def composed(front, back, dz, depth, rgb, K, baseline) -> dict[str, torch.Tensor]:
    """The model's composer call (``StereoGaussians.compose``): the branches cast to float32, paper options."""
    return compose(front.float(), back.float(), dz.float(), depth, rgb, K, baseline)


def back_depth_of(front, back, dz, depth, rgb, K, baseline) -> dict[str, torch.Tensor]:
    return {"back depth": back_depth(depth, dz.float())}


def inputs(batch: int, side: int, device: torch.device) -> list[torch.Tensor]:
    """Random composer inputs of one seed: branches [B, 37, side, side] bf16 channels-last (as the predictor's
    fused output gives them), dz, a depth in metres with a far block (an edge), RGB, K, baseline (metres)."""
    g = torch.Generator(device="cpu").manual_seed(0)

    def randn(*shape):
        return torch.randn(*shape, generator=g).to(device)

    branches = [(randn(batch, LAYER_CHANNELS + 3, side, side) * 2).to(torch.bfloat16)
                .contiguous(memory_format=torch.channels_last)[:, :LAYER_CHANNELS] for _ in range(2)]
    dz = randn(batch, 1, side, side).to(torch.bfloat16)
    depth = torch.rand(batch, 1, side, side, generator=g).to(device) * 5 + 0.2
    depth[:, :, side // 4:side // 2, side // 2:] = 9.5
    rgb = torch.rand(batch, 3, side, side, generator=g).to(device)
    f = side * 1.1
    K = torch.tensor([[f, 0, side / 2], [0, f, side / 2], [0, 0, 1]], device=device).expand(batch, 3, 3).contiguous()
    return [*branches, dz, depth, rgb, K, torch.full((batch,), 0.12, device=device)]


def run(fn, args: list[torch.Tensor]) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
    """Outputs of ``fn`` and the gradients of front, back and dz of a fixed random projection of them."""
    leaves = [a.detach().clone().requires_grad_(i < 3) for i, a in enumerate(args)]
    out = fn(*leaves)
    g = torch.Generator(device="cpu").manual_seed(1)
    loss = sum((v.float() * torch.randn(v.shape, generator=g).to(v.device)).sum() for _, v in sorted(out.items()))
    grads = torch.autograd.grad(loss, leaves[:3], allow_unused=True)
    return {k: v.detach() for k, v in out.items()}, [torch.zeros_like(x) if d is None else d
                                                      for x, d in zip(leaves, grads)]


def distance(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-300))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batches", type=int, nargs="+", default=[1, 4, 16, 32])
    p.add_argument("--canvas", type=int, default=288, help="canvas pixels a side (256 + 2 x 16 for the paper model)")
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    args = p.parse_args(argv)
    out = OwnedFile(args.out, "--out", "scripts/checks/compiled_composer.py")
    device = torch.device(args.device)
    lines = [f"`compose` and `back_depth` compiled (inductor, static shapes) against eager, random inputs at "
             f"{args.canvas}x{args.canvas}, on {device.type}"
             f"{' (' + torch.cuda.get_device_name(device) + ')' if device.type == 'cuda' else ''}, torch "
             f"{torch.__version__}: relative L2 distance of each output, and of the gradients of front, back, dz.",
             "", "| function | batch | output or gradient | compiled vs eager |", "|---|---:|---|---:|"]
    for fn in (back_depth_of, composed):
        compiled = torch.compile(fn, dynamic=False)
        for batch in args.batches:
            x = inputs(batch, args.canvas, device)
            (want, want_g), (got, got_g) = run(fn, x), run(compiled, x)
            rows = [(k, distance(got[k], want[k])) for k in want]
            rows += [(f"d/d {n}", distance(a, b)) for n, a, b in zip(("front", "back", "dz"), got_g, want_g)
                     if b.abs().sum() > 0]
            for name, d in rows:
                lines.append(f"| {fn.__name__} | {batch} | {name} | {d:.2e} |")
            print("\n".join(lines[-len(rows):]), flush=True)
    report("\n".join(lines) + "\n", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
