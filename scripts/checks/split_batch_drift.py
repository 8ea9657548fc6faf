"""How far a global batch computed in shares drifts from the same batch computed whole, in float32 and under
bf16 autocast: the part of the several-GPU weight difference that is not a bug (issue 34).

    python scripts/checks/split_batch_drift.py --data DATASET [--steps 40] [--batch-size 8] [--shares 2 4]
                                               [--device cpu] [--cudnn-benchmark] [--out report.md]

DDP on R ranks computes each step's gradient as the mean of R shares' gradients; one process computes it
over the whole batch at once. In exact arithmetic they are equal (the CPU test of
``tests/sgmodel/train/test_distributed.py`` holds them to 6e-7 in float32). Under bf16 autocast every
convolution's weight gradient of a share is rounded to bf16 (8 significant bits) before the shares are
summed in float32, and the kernels chosen for a share's batch shape need not be those of the whole batch;
AdamW then divides each gradient by its own running magnitude, so a relative rounding of 2^-9 in a gradient
that is near zero becomes a step of up to ``lr`` in its weight. Two runs of one process on the same shapes
(``scripts/checks/ddp_check.py --noise-floor``) see neither effect.

This script trains one model from one seed for ``--steps`` steps on the same batches (``make_loader`` at
``--batch-size``, the targets ``sgmodel train`` draws), in each precision: float32; "bf16 gradients", float32
with every parameter's gradient of each backward rounded to bf16 before it is accumulated (what autocast does
to a weight gradient, alone: runs on any device; PyTorch's CPU autocast lacks the decoder's antialiased
bf16 resize); and on CUDA bf16 autocast itself. Three ways in each: whole; in
``--shares`` equal shares whose gradients are averaged, as DDP averages its ranks' (gradient accumulation on
one process: the all-reduce left out); and whole again (this device's own run-to-run floor). It reports
||w - w_whole|| / ||w_whole|| over all parameters (``ddp_check.weight_difference``) after the first step and
the last.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from scenesplat_stereo.common.ownership import OwnedFile
from scripts.checks.ddp_check import weight_difference
from sgmodel.args import preset_params
from sgmodel.bench import report
from sgmodel.data.loader import make_loader, to_device
from sgmodel.model.network import create_model
from sgmodel.train.step import create_optimizer, train_step
from sgmodel.train.losses import create_objective


#: precision -> (bf16 autocast, gradients rounded to bf16)
PRECISIONS = {"float32": (False, False), "bf16 gradients": (False, True), "bf16 autocast": (True, False)}


def run(model0, batches: list[dict], objective, shares: int, precision: str, lr: float) -> list[dict]:
    """Train a copy of ``model0`` on ``batches`` with ``sgmodel train``'s step (``train_step``), each step's
    gradient the mean over ``shares`` equal shares (its ``accumulate``), at a constant ``lr``. The weights after
    every step."""
    model = copy.deepcopy(model0).train()
    params = [p for p in model.parameters() if p.requires_grad]
    autocast, round_grads = PRECISIONS[precision]
    if round_grads:
        for param in params:
            param.register_hook(lambda g: g.to(torch.bfloat16).to(g.dtype))
    optimizer = create_optimizer(params, batches[0]["left"].device, lr=lr)
    constant = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
    history = []
    for batch in batches:
        train_step(model, batch, objective, optimizer, constant, autocast, accumulate=shares)
        history.append({k: v.detach().clone() for k, v in model.state_dict().items() if v.is_floating_point()})
    return history


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="a dataset built by `scenesplat-stereo build`")
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--batch-size", type=int, default=8, help="pairs a step (divisible by every share count)")
    p.add_argument("--shares", type=int, nargs="+", default=[2, 4], help="share counts (the ranks DDP would use)")
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--preset", default="cpu-small")
    p.add_argument("--lr", type=float, help="AdamW's learning rate, constant (default: the preset's peak)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--cudnn-benchmark", action="store_true",
                   help="let cuDNN time its algorithms per shape, as `sgmodel train` does on CUDA (default: its "
                        "heuristics; a share's batch shape may then get another algorithm family)")
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    args = p.parse_args(argv)
    if any(args.batch_size % s for s in args.shares):
        p.error(f"--batch-size {args.batch_size} is not divisible by every --shares {args.shares}")
    out = OwnedFile(args.out, "--out", "scripts/checks/split_batch_drift.py")  # before any run
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = args.cudnn_benchmark
    model_params, train_params = preset_params(args.preset)
    args.lr = args.lr or train_params.lr
    model_params.resolution, model_params.padding = args.resolution, max(2, args.resolution // 16)
    torch.manual_seed(0)
    model0 = create_model(model_params, device)
    loader = make_loader(args.data, "train", args.batch_size, args.resolution, train_params.targets, seed=0)
    batches, stream = [], iter(loader)
    for _ in range(args.steps):
        batches.append(to_device(next(stream), device))
    objective = create_objective(None)
    lines = [f"Whole batch against shares, {args.steps} AdamW steps (lr {args.lr:g}) of the `{args.preset}` model at "
             f"{args.resolution}x{args.resolution}, batch {args.batch_size}, on {device}"
             f"{' (cuDNN autotuned)' if args.cudnn_benchmark else ''}: relative L2 distance of all "
             "weights from the whole batch's run of the same precision.", "",
             "| precision | run | after step 1 | after the last step |", "|---|---|---:|---:|"]
    for name in [n for n in PRECISIONS if device.type == "cuda" or not PRECISIONS[n][0]]:
        whole = run(model0, batches, objective, 1, name, args.lr)
        for label, shares in [("whole again (run-to-run floor)", 1),
                              *((f"{s} shares (what {s} ranks compute)", s) for s in args.shares)]:
            other = run(model0, batches, objective, shares, name, args.lr)
            lines.append(f"| {name} | {label} | {weight_difference(whole[0], other[0]):.2e} | "
                         f"{weight_difference(whole[-1], other[-1]):.2e} |")
            print(lines[-1], flush=True)
    report("\n".join(lines) + "\n", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
