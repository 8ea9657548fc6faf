"""DDP's gradient at the first step against one process's, on the machine `sgmodel train` runs on (issue 34):
the GPU counterpart of tests/sgmodel/train/test_distributed.py's gloo check, with what training runs on CUDA
(NCCL, cuDNN autotuning).

    torchrun --standalone --nproc_per_node 2 scripts/checks/ddp_gradient.py --data DATASET [--batch-size 32]
        [--resolution 256] [--preset paper] [--amp] [--out report.md]

Every rank builds the model from one seed, wraps it in DDP as ``sgmodel train`` does (``wrap_model``) and runs
step 0's forward and backward on its share of the global batch (``train_step``, its optimiser moving nothing).
Rank 0 keeps the all-reduced gradient, then computes the same global batch again in this one process, on a
model built from the same seed (with the cuDNN algorithms its DDP share ran): whole, in as many shares as
there are ranks (``train_step``'s ``accumulate``), and the shares again (this process's run-to-run floor). The
report gives the relative L2 distance of the gradients, ||g - g_ref|| / ||g_ref||, over all parameters and for
the parameters farthest apart. Nothing is trained: the weights' drift over many steps (``ddp_check.py``)
amplifies such a first-step difference, and this shows where it starts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from scenesplat_stereo.common.ownership import OwnedFile
from sgmodel.args import preset_params
from sgmodel.bench import report
from sgmodel.data.loader import make_loader, to_device
from sgmodel.model.network import create_model
from sgmodel.train.distributed import joined_world, wrap_model
from sgmodel.train.step import train_step
from sgmodel.train.losses import create_objective

SEED = 0


def gradient(model, net, batch: dict, objective, amp: bool, shares: int) -> dict[str, torch.Tensor]:
    """The gradient ``sgmodel train``'s step (``train_step``, in ``shares`` shares) leaves on ``model``'s
    parameters for ``batch``, run through ``net`` (``model`` itself or its DDP wrapper), as float64 copies. Its
    optimiser moves no weight (SGD at a learning rate of 0)."""
    still = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.0)
    train_step(net, batch, objective, still, torch.optim.lr_scheduler.LambdaLR(still, lambda _: 1.0), amp,
               accumulate=shares)
    return {n: p.grad.double().clone() for n, p in model.named_parameters() if p.grad is not None}


def distance(a: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> float:
    num = sum(float(((a[n] - g) ** 2).sum()) for n, g in ref.items())
    return (num / sum(float((g**2).sum()) for g in ref.values())) ** 0.5


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="a dataset built by `scenesplat-stereo build`")
    p.add_argument("--batch-size", type=int, default=32, help="the global batch (pairs over all ranks)")
    p.add_argument("--resolution", type=int, default=256)
    p.add_argument("--preset", default="paper", help="the model's preset (`sgmodel train --preset`; default paper)")
    p.add_argument("--device", default="cuda", help="cuda (NCCL) or cpu (gloo)")
    p.add_argument("--amp", action="store_true", help="bf16 autocast (default float32)")
    p.add_argument("--top", type=int, default=8, help="parameters listed, farthest first")
    p.add_argument("--out", type=Path, help="also write the markdown report here (rank 0)")
    args = p.parse_args(argv)
    out = OwnedFile(args.out, "--out", "scripts/checks/ddp_gradient.py")
    with joined_world(args.device) as world:  # left, every rank waited for, once DDP's gradient is taken
        if args.batch_size % world.size:
            p.error(f"--batch-size {args.batch_size} is not divisible by the {world.size} ranks")
        torch.backends.cudnn.benchmark = world.device.type == "cuda"  # as `sgmodel train` does
        model_params, train_params = preset_params(args.preset)
        model_params.resolution, model_params.padding = args.resolution, max(2, args.resolution // 16)  # P = 16 at 256
        targets = train_params.targets
        objective = create_objective(None, device=world.device)

        def fresh():
            torch.manual_seed(SEED)
            return create_model(model_params, world.device)

        def first_batch(ranks: int, rank: int) -> dict:
            loader = make_loader(args.data, "train", args.batch_size // ranks, args.resolution, targets, seed=SEED,
                                 rank=rank, world_size=ranks)
            return to_device(next(iter(loader)), world.device)

        model = fresh()
        ddp = gradient(model, wrap_model(model, world), first_batch(world.size, world.rank), objective, args.amp, 1)
    if not world.main:
        return 0
    whole = first_batch(1, 0)
    runs = {"one process, whole batch": gradient(m := fresh(), m, whole, objective, args.amp, 1)}
    for label in (f"one process, {world.size} shares", f"one process, {world.size} shares again"):
        runs[label] = gradient(m := fresh(), m, whole, objective, args.amp, world.size)
    ref = runs[f"one process, {world.size} shares"]
    runs[f"DDP, {world.size} ranks"] = ddp
    lines = [f"First-step gradient of the {args.preset} model at {args.resolution}x{args.resolution}, global batch "
             f"{args.batch_size}, {'bf16 autocast' if args.amp else 'float32'}, on {world.device.type} "
             f"({torch.cuda.get_device_name(world.device) if world.device.type == 'cuda' else 'CPU'}): relative L2 "
             "distance of all parameters' gradients.", "",
             "| gradient | vs the whole batch | vs the same shares in one process |", "|---|---:|---:|"]
    for label, g in runs.items():
        lines.append(f"| {label} | {distance(g, runs['one process, whole batch']):.2e} | {distance(g, ref):.2e} |")
    lines += ["", f"DDP against the same shares in one process, the {args.top} parameters farthest apart:", "",
              "| parameter | elements | rel. L2 | ref. norm |", "|---|---:|---:|---:|"]
    far = sorted(ref, key=lambda n: -float((ddp[n] - ref[n]).norm() / ref[n].norm().clamp_min(1e-300)))
    for n in far[:args.top]:
        lines.append(f"| {n} | {ref[n].numel()} | {float((ddp[n] - ref[n]).norm() / ref[n].norm()):.2e} | "
                     f"{float(ref[n].norm()):.3e} |")
    report("\n".join(lines) + "\n", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
