"""Several GPUs, measured and checked in one go (the recipe behind ``scripts/gpu/scale.sh``; also run on the
CPU with gloo by ``tests/sgmodel/train/test_distributed.py``).

    python scripts/checks/ddp_check.py --data DATASET --work DIR --ranks 2 [4 ...] [--device cuda] [--steps 200]
                                       [--weak-ranks 2 4] [--noise-floor] [--split-floor] [--no-resume] [--profile]
                                       [--label TEXT] [--out report.md] [-- extra `sgmodel train` flags]

Runs, each with the same flags and seed (``--val-every`` a quarter of ``--steps``):

1. one process, uninterrupted (the reference, and the one-GPU throughput);
2. with ``--noise-floor``, one process again: how far two runs of the same seed drift apart on this device
   (bf16 autocast, cuDNN's and the rasteriser's nondeterministic summation order), the floor against which
   the several-rank runs' difference is read;
3. for each of ``--ranks``, ``torchrun --nproc_per_node=RANKS``, uninterrupted (the throughput; its weights
   against 1); with ``--split-floor`` also one process with ``--accumulate RANKS``: the same shares of each
   batch that the RANKS ranks compute, one after another in one process, their gradients averaged. DDP's
   weights are read against that run too: what DDP itself (other processes, NCCL) adds to the split;
4. for each of ``--weak-ranks``, RANKS processes at ``--batch-size`` pairs each (RANKS x that a step: the
   paper's "effective batch = GPUs x per-GPU batch", each GPU as full as the one-process run's), throughput
   only (a different batch trains other weights);
5. unless ``--no-resume``, with the first of ``--ranks``: RANKS processes stopped (SIGKILL, every rank) at
   their first checkpoint, resumed on one process; one process stopped at its first checkpoint, resumed on
   RANKS processes.

Throughput is pairs per second from the median ``step_ms`` of ``metrics.jsonl`` (the first ``--skip`` steps
left out: cuDNN autotuning, Triton compilation, loader start-up), ``--batch-size`` pairs a step over all
ranks (``--weak-ranks``: RANKS x ``--batch-size``). Weights are compared as ||difference|| / ||weights|| over all
parameters (``weight_difference``):
DDP averages the ranks' gradients, which equals one process's mean up to float summation order
(``tests/sgmodel/train/test_distributed.py`` holds the gradients of one step to that on the CPU). With ``--profile`` the
runs record each rank's step phases (``sgmodel.train.step_profile``) and the report adds their medians.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from scenesplat_stereo.common.ownership import OwnedFile
from sgmodel.bench import report

REPO = Path(__file__).resolve().parents[2]


def command(ranks: int, data: Path, run: Path, flags: list[str]) -> list[str]:
    """``sgmodel train`` on one process, or under ``torchrun`` on ``ranks`` processes of this host."""
    train = ["-m", "sgmodel.cli", "train", "--data", str(data), "--out", str(run), *flags]
    if ranks == 1:
        return [sys.executable, *train]
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}", *train]


def train(ranks: int, data: Path, run: Path, flags: list[str]) -> subprocess.CompletedProcess:
    """Run to the end; RuntimeError with the end of stderr if it fails."""
    done = subprocess.run(command(ranks, data, run, flags), capture_output=True, text=True, cwd=REPO)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command(ranks, data, run, flags))} failed ({done.returncode}):\n"
                           f"{done.stderr[-3000:]}")
    return done


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (torchrun starts its ranks in sessions of their own)."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        for child in (task / "children").read_text().split():
            out += [int(child), *_descendants(int(child))]
    return out


def stop_at_first_checkpoint(ranks: int, data: Path, run: Path, flags: list[str]) -> int:
    """Start a run and SIGKILL it, every rank included, as soon as ``last.pt`` exists; the step it holds.
    The process tree is frozen (SIGSTOP) first, so no rank writes after the checkpoint is read."""
    proc = subprocess.Popen(command(ranks, data, run, flags), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            cwd=REPO)
    last = run / "checkpoints" / "last.pt"
    while not last.exists() and proc.poll() is None:
        time.sleep(0.01)
    tree = [proc.pid, *_descendants(proc.pid)]
    for sig in (signal.SIGSTOP, signal.SIGKILL):
        for pid in tree:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
    proc.wait()
    if not last.exists():
        raise RuntimeError(f"{run}: no checkpoint was written:\n{proc.stderr.read().decode()[-3000:]}")
    return int(torch.load(last, weights_only=True)["step"])


def last_weights(run: Path) -> tuple[int, dict[str, torch.Tensor]]:
    """(step, trainable state_dict) of ``run/checkpoints/last.pt``."""
    ckpt = torch.load(run / "checkpoints" / "last.pt", weights_only=True, map_location="cpu")
    return int(ckpt["step"]), ckpt["model"]


def weight_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    """||a - b|| / ||a|| over all parameters together (float64). Not a per-element maximum: AdamW's first
    steps move each weight by about lr * sign(gradient), so a gradient that is float noise around zero
    flips a few elements by a whole step whatever the world size."""
    if a.keys() != b.keys():
        raise ValueError(f"different parameters: {sorted(a.keys() ^ b.keys())}")
    diff = sum(float(((a[k].double() - b[k].double()) ** 2).sum()) for k in a)
    return (diff / max(sum(float((a[k].double() ** 2).sum()) for k in a), 1e-300)) ** 0.5


def records(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]


def pairs_per_second(run: Path, batch: int, skip: int) -> tuple[float, float]:
    """(pairs/s, median step ms) over the training records after step ``skip``."""
    ms = [r["step_ms"] for r in records(run) if "step_ms" in r and r["step"] > skip]
    if not ms:
        raise ValueError(f"{run}/metrics.jsonl: no step_ms records after step {skip}")
    median = statistics.median(ms)
    return batch / (median / 1e3), median


def profile_rows(run: Path, skip: int) -> list[str]:
    """Markdown rows: each rank's median phase times (ms) after step ``skip``, and its validation time."""
    from sgmodel.train.step_profile import PHASES

    steps = [r for r in records(run) if "forward" in r and r["step"] > skip]
    if not steps:
        return []
    val = [r["val_ms"] for r in records(run) if "val_ms" in r and r["step"] > 0]
    writes = [r["write_ms"] for r in records(run) if "write_ms" in r and r["step"] > 0]
    rows = []
    for rank in range(len(steps[0]["forward"])):
        cells = [statistics.median(r[k][rank] for r in steps) for k in PHASES]
        cells += [statistics.median(v[rank] for v in val) if val else float("nan"),
                  statistics.median(writes) if writes and rank == 0 else 0.0]
        rows.append(f"| {run.name} | {rank} | " + " | ".join(f"{c:.1f}" for c in cells) + " |")
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument("--data", type=Path, required=True, help="a dataset built by `scenesplat-stereo build`")
    p.add_argument("--work", type=Path, required=True, help="folder for the runs (created)")
    p.add_argument("--ranks", type=int, nargs="+", default=[2], help="processes (GPUs) of the several-GPU runs "
                                                                     "(default 2)")
    p.add_argument("--weak-ranks", type=int, nargs="*", default=[],
                   help="processes of runs at --batch-size pairs per rank (throughput at a full GPU each)")
    p.add_argument("--device", default="cuda", help="cuda (NCCL) or cpu (gloo)")
    p.add_argument("--steps", type=int, default=200, help="steps of every run (default 200)")
    p.add_argument("--batch-size", type=int, default=32, help="pairs a step over all ranks (default 32)")
    p.add_argument("--skip", type=int, default=20, help="steps left out of the throughput (default 20)")
    p.add_argument("--noise-floor", action="store_true", help="a second one-process run of the same seed")
    p.add_argument("--split-floor", action="store_true",
                   help="for each of --ranks, one process computing the same shares (`--accumulate RANKS`)")
    p.add_argument("--no-resume", action="store_true", help="leave out the stopped-and-resumed runs")
    p.add_argument("--profile", action="store_true", help="`sgmodel train --profile`: a table of step phases")
    p.add_argument("--label", default="", help="a word for the report's first line (e.g. 'encoder cache')")
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    p.add_argument("extra", nargs=argparse.REMAINDER, help="after --: more `sgmodel train` flags")
    args = p.parse_args(argv)
    report_out = OwnedFile(args.out, "--out", "scripts/checks/ddp_check.py")  # before any run
    extra = args.extra[1:] if args.extra[:1] == ["--"] else args.extra

    def flags_at(batch: int) -> list[str]:
        return ["--device", args.device, "--steps", str(args.steps), "--batch-size", str(batch),
                "--val-every", str(max(1, args.steps // 4)), "--log-every", "1", "--no-progress", *extra,
                *(["--profile"] if args.profile else [])]

    flags = flags_at(args.batch_size)
    work, first = args.work, args.ranks[0]
    one = work / "one"
    train(1, args.data, one, flags)
    again = work / "one-again"
    if args.noise_floor:
        train(1, args.data, again, flags)
    many = {r: work / f"ranks{r}" for r in args.ranks}
    for r, run in many.items():
        train(r, args.data, run, flags)
    split = {r: work / f"shares{r}" for r in args.ranks} if args.split_floor else {}
    for r, run in split.items():
        train(1, args.data, run, [*flags, "--accumulate", str(r)])
    weak = {r: work / f"weak{r}" for r in args.weak_ranks}
    for r, run in weak.items():
        train(r, args.data, run, flags_at(r * args.batch_size))
    resumed = {}
    if not args.no_resume:
        resumed = {f"{first} processes, resumed on 1": (first, 1, work / f"{first}to1"),
                   f"1 process, resumed on {first}": (1, first, work / f"1to{first}")}
        stopped = {label: stop_at_first_checkpoint(a, args.data, run, flags) for label, (a, _, run) in resumed.items()}
        for label, (_, b, run) in resumed.items():
            train(b, args.data, run, flags)

    one_pps, one_ms = pairs_per_second(one, args.batch_size, args.skip)
    reference = last_weights(one)[1]
    lines = [f"`sgmodel train` on {args.device}{', ' + args.label if args.label else ''}, {args.steps} steps, batch "
             f"{args.batch_size} over all ranks{' (and, in the rows of --weak-ranks, per rank)' if weak else ''}, "
             "flags "
             f"`{' '.join(extra)}`; throughput from the median step after step {args.skip}.", "",
             "| processes | pairs a step | median step (ms) | pairs/s | speed-up |", "|---:|---:|---:|---:|---:|",
             f"| 1 | {args.batch_size} | {one_ms:.1f} | {one_pps:.1f} | 1.00 |"]
    for r, run, batch in [*((r, run, args.batch_size) for r, run in many.items()),
                          *((r, run, r * args.batch_size) for r, run in weak.items())]:
        pps, ms = pairs_per_second(run, batch, args.skip)
        lines.append(f"| {r} | {batch} ({batch // r} per rank) | {ms:.1f} | {pps:.1f} | {pps / one_pps:.2f} |")
    lines += ["", "| run | stopped at step | final step | weights vs one process (rel. L2 diff) | "
              "vs the same shares in one process |", "|---|---:|---:|---:|---:|"]
    if args.noise_floor:
        step, w = last_weights(again)
        lines.append(f"| 1 process again, same seed (the noise floor) | - | {step} | "
                     f"{weight_difference(reference, w):.2e} | - |")
    for r, run in split.items():
        step, w = last_weights(run)
        lines.append(f"| 1 process, {r} shares (`--accumulate {r}`) | - | {step} | "
                     f"{weight_difference(reference, w):.2e} | - |")
    for r, run in many.items():
        step, w = last_weights(run)
        shares = f"{weight_difference(last_weights(split[r])[1], w):.2e}" if r in split else "-"
        lines.append(f"| {r} processes, uninterrupted | - | {step} | {weight_difference(reference, w):.2e} | "
                     f"{shares} |")
    for label, (_, _, run) in resumed.items():
        step, w = last_weights(run)
        lines.append(f"| {label} | {stopped[label]} | {step} | {weight_difference(reference, w):.2e} | - |")
    if args.profile:
        from sgmodel.train.step_profile import PHASES

        lines += ["", f"Per rank, median ms of a step after step {args.skip} (`--profile`; GPU phases are stream "
                  "time between CUDA events; allreduce: the all-reduce's exposed part after the last gradient; "
                  "cache_mb: encoder-cache MiB a step), validation ms per rank, and rank 0's writes (sheet, "
                  "checkpoints) while the others wait:", "",
                  "| run | rank | " + " | ".join(PHASES) + " | validation | rank-0 writes |",
                  "|---|---:|" + "---:|" * (len(PHASES) + 2)]
        for run in [one, *many.values(), *weak.values()]:
            lines += profile_rows(run, args.skip)
    report("\n".join(lines) + "\n", report_out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
