"""``sgmodel train``: train the model on SceneSplat-Stereo shards (the loop: ``sgmodel.train.loop``).

The loop reads shards through ``sgmodel.data.loader``, predicts Gaussians with the model, renders every target
through ``sgmodel.model.render`` (our Warp rasteriser and its hand-written backward), and minimises
MSE + 0.05 LPIPS-VGG (or MSE + 0.05 (1 - SSIM) without the VGG weights) with AdamW and OneCycleLR
(SPEC section 7). Every ``val_every`` steps it validates on the whole validation split, writes a contact
sheet (input, depth, targets, renders) and keeps the checkpoint with the highest validation PSNR.

Files in RUN (only rank 0 writes, every file atomically): ``config.json`` (all settings, the encoder and
its weights hash, the loss used), ``metrics.jsonl`` (one record per ``log_every`` steps: step, loss, psnr,
lr, step_ms; one per validation: step, val_psnr, val_psnr_masked, val_targets and
val_targets_without_valid_pixels, the targets left out of val_psnr_masked, which is null when no target has
a valid pixel; whole lines only), ``checkpoints/last.pt`` and ``best.pt`` (``sgmodel.model.checkpoint``),
``sheets/val_<step>.png``, and ``.lock`` while a process trains in it (a second one is refused). An
interrupted or killed run resumes from ``last.pt`` exactly: weights, optimiser, scheduler, RNG and the data
order (a function of seed and step); a torn last line of ``metrics.jsonl`` is dropped with a warning.

Nothing is written before every input is checked: the flags, ``--out`` (a folder that can be written, not
inside ``--data``, empty, or a run of the same settings), both splits (their first samples decoded at
the run's size, and a valid pixel in some target of each), the encoder and LPIPS weights, ``--init-from``,
``--encoder-cache`` (``sgmodel.data.encoder_cache``: it must fit the encoder, the resolution, the precision
and the data). A RUN that holds an earlier attempt of other settings without any checkpoint is started
afresh (nothing of value is lost).

Divergence: the loss is checked every step, when the loop reads the step's values (``StepValues``: once the next
step is queued, at once at a log or checkpoint step; on a GPU a non-finite loss has already made its own update
skip itself on the device); the gradients every step with one fused norm on the device (no sync), read together
with the weights' norm at every log and checkpoint step. A NaN or infinity stops training with
``TrainingDiverged``, before any checkpoint holds it; ``--init-from last.pt`` starts a new run with other
settings from the last finite weights. A run that diverges ends with the command that goes on from its last
checkpoint at half the learning rate (``restart_command``).
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from sgmodel.args import (add_device_argument, add_model_arguments, add_train_arguments, device_from_flag,
                          params_from_args)
from sgmodel.train import loop


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="dataset folder written by `scenesplat-stereo build`")
    p.add_argument("--out", type=Path, required=True, help="run folder (created; an existing run resumes)")
    p.add_argument("--init-from", type=Path, metavar="CKPT",
                   help="start a new run from this checkpoint's weights (not its optimiser or step), e.g. the "
                        "last.pt of a diverged run, with other settings")
    p.add_argument("--encoder-cache", type=Path, metavar="CACHE",
                   help="read the frozen encoder's outputs from this cache of --data (`sgmodel encode`) instead of "
                        "running the encoder every step; the same numbers, a faster step")
    add_device_argument(p)
    p.add_argument("--lpips-vgg", help="torchvision VGG16 ImageNet weights vgg16-397923af.pth (default: torch's hub "
                                       "cache); without them the LPIPS term becomes 1 - SSIM")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_model_arguments(p)
    add_train_arguments(p)


def run(args: argparse.Namespace) -> int:
    model, tp = params_from_args(args)
    try:
        loop.train(model, tp, args.data, args.out, device=device_from_flag(args.device), vgg_path=args.lpips_vgg,
                   progress=not args.no_progress, init_from=args.init_from, encoder_cache=args.encoder_cache)
    except loop.TrainingDiverged as e:
        raise loop.TrainingDiverged(f"{e}; the command: {restart_command(args.command_argv, e, args.out)}",
                                    e.step, e.checkpoint, e.checkpoint_step, e.lr) from None
    return 0


def restart_command(argv: list[str], e, out: Path) -> str:
    """The ``sgmodel train`` command that goes on after the divergence ``e`` of the run typed as ``argv``: the
    same flags with half the learning rate, from the last checkpoint into a new run folder when there is one
    (``--init-from``), else again in the same folder (which saved nothing)."""
    drop, kept, skip = {"--out", "--lr", "--init-from"}, [], False
    for word in argv:
        if skip:
            skip = False
        elif word in drop:
            skip = True
        elif word.split("=", 1)[0] not in drop:
            kept.append(word)
    new_out, extra = out, []
    if e.checkpoint is not None:
        n, new_out = 1, out.with_name(f"{out.name}-from-{e.checkpoint_step}")
        while new_out.exists():
            n += 1
            new_out = out.with_name(f"{out.name}-from-{e.checkpoint_step}-{n}")
        extra = ["--init-from", str(e.checkpoint)]
    return shlex.join(["sgmodel", *kept, "--out", str(new_out), "--lr", f"{e.lr / 2:g}", *extra])
