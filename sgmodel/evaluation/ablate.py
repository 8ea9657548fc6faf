"""``sgmodel ablate``: the paper's Table 4 on your data, with one shared schedule.

Trains the default model and each switch of Table 4 (blocks A, C and D; block B, another encoder, is
``--encoder`` on a whole run), evaluates each best checkpoint on the validation split, adds the two
baselines without learned prediction as extra rows, and writes ``OUT/table.md`` in the Table 4 layout.
Every variant lives in ``OUT/<variant>/`` (``run/`` from ``sgmodel train``, ``eval/`` from ``sgmodel eval``),
so an interrupted ablation resumes where it stopped: finished evaluations are read back, runs resume.

Padding variants are multiples of the default padding P (paper: 0, 32 and 64 pixels beside P = 16 at
S = 256, i.e. 0, 2P and 4P), so a smaller preset keeps the paper's proportions.

Before anything is written: the flags, every ``--only`` word (each must match a variant or a baseline),
the data (both splits' first samples at the run's size), ``--encoder-cache`` (it must fit the encoder, the
resolution and the precision; every variant's run reads it, Table 4's blocks A, C and D keep the encoder),
and OUT (a folder that can be written, not inside the data, and new, empty or an earlier ablation: every file
in it one an ablation wrote, unchanged; ``scenesplat_stereo.common.ownership.check_replaceable``, the one owner
of "may this command replace what is there"). One ablation at a time writes OUT (``OUT/.lock``); its files are recorded
as the ablation's when it ends, however it ends (``OwnedFolder``: a killed ablation's rerun resumes).
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

from scenesplat_stereo.common.files import atomic_write_bytes, read_json
from scenesplat_stereo.common.ownership import FolderLock, OwnedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import markdown_table, value_cell
from sgmodel.args import (add_device_argument, add_model_arguments, add_train_arguments, device_from_flag,
                          params_from_args)
from sgmodel.config import ConfigurationError, ModelParams, TrainParams
from sgmodel.encoders.flags import build_encoder
from sgmodel.evaluation import evaluate
from sgmodel.train.loop import open_run_cache, read_split_checked, train

OWNER = "sgmodel ablate"  # recorded in OUT's manifest (ownership.OWNER_FILE): a later ablation may resume or replace it


def variants(base: ModelParams) -> list[tuple[str, str, ModelParams]]:
    """(block, name, params) of every Table 4 row we train; the first is the shared default."""

    def edit(**changes) -> ModelParams:
        p = copy.deepcopy(base)
        for path, value in changes.items():
            obj, *rest = path.split("__")
            if rest:
                setattr(getattr(p, obj), rest[0], value)
            else:
                setattr(p, obj, value)
        return p

    P = base.padding
    return [
        ("", "Shared default", copy.deepcopy(base)),
        ("(A) Input conditioning", "Without descriptor", edit(descriptor=False)),
        ("(A) Input conditioning", "Without RGB-D conditioning", edit(rgbd=False)),
        ("(C) Gaussian prediction design", "Without back layer", edit(composer__back_layer=False)),
        ("(C) Gaussian prediction design", "Hard edge mask", edit(composer__edge_mask="hard")),
        ("(C) Gaussian prediction design", "Soft edge mask", edit(composer__edge_mask="soft")),
        ("(C) Gaussian prediction design", "Without composer", edit(composer__composer=False)),
        ("(D) FoV padding per side", "without padding", edit(padding=0)),
        ("(D) FoV padding per side", f"{2 * P} pixels", edit(padding=2 * P)),
        ("(D) FoV padding per side", f"{4 * P} pixels", edit(padding=4 * P)),
    ]


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name.lower()).strip("-")


def _evaluated(folder: Path, make_method, data: Path, device: str, lpips_vgg: str | None, progress: bool) -> dict:
    done = folder / "metrics.json"
    if done.exists():
        return read_json(done)
    return evaluate.evaluate(make_method(), data, "val", folder, device, lpips_vgg, progress=progress)


def ablate(base: ModelParams, schedule: TrainParams, data: Path, out: Path, device: str, lpips_vgg: str | None,
           only: list[str] | None = None, progress: bool = True, encoder_cache: Path | None = None) -> str:
    """Train and evaluate every variant (or those whose names contain one of ``only``); returns table.md.
    ``encoder_cache``: the encoder's outputs on ``data`` (``sgmodel encode``), read by every variant's run
    (they share the encoder and the resolution)."""
    t0 = time.perf_counter()
    check_ablation(base, schedule, data, out, only)
    if encoder_cache is not None:
        open_run_cache(encoder_cache, data, build_encoder(base.encoder, device), base.resolution, device,
                       schedule.amp)
    with FolderLock(out, "--out", OWNER), OwnedFolder(out, OWNER):  # every file in OUT recorded as the ablation's
        return _ablate(base, schedule, data, out, device, lpips_vgg, only, progress, t0, encoder_cache)


def check_ablation(base: ModelParams, schedule: TrainParams, data: Path, out: Path, only: list[str] | None) -> None:
    """Everything ``ablate`` can check before it writes (ValueError naming the flag): see the module docstring."""
    names = [name for _, name, _ in variants(base)] + list(evaluate.METHODS)
    for word in only or []:
        if not any(word.lower() in name.lower() for name in names):
            raise ValueError(f"--only {word!r}: matches no variant; the variants are {', '.join(names)}")
    base.validate()
    schedule.validate()
    check_apart(out, "--out", {"--data": data})
    check_replaceable(out, "--out", OWNER)  # new, empty, or an earlier ablation's files only (it resumes)
    read_split_checked(data, base.resolution, schedule.targets)


def _ablate(base: ModelParams, schedule: TrainParams, data: Path, out: Path, device: str, lpips_vgg: str | None,
            only: list[str] | None, progress: bool, t0: float, encoder_cache: Path | None) -> str:
    rows = []
    for block, name, params in variants(base):
        if only and not any(o.lower() in name.lower() for o in only):
            continue
        folder = out / _slug(name)
        print(f"== {name} ==", flush=True)
        try:
            train(params, copy.deepcopy(schedule), data, folder / "run", device, lpips_vgg, progress,
                  encoder_cache=encoder_cache)
        except ConfigurationError as e:  # e.g. no RGB-D with an encoder that has no features
            rows.append((block, name, {"not_applicable": str(e)}))
            continue
        result = _evaluated(folder / "eval", lambda: evaluate.checkpoint_method(
            folder / "run" / "checkpoints" / "best.pt", device, params.encoder.weights, params.encoder.repo), data,
            device, lpips_vgg, progress)
        rows.append((block, name, result))
    for method in evaluate.METHODS:
        result = _evaluated(out / f"baseline-{method}", lambda: evaluate.baseline_method(
            method, base.encoder, base.resolution, device), data, device, lpips_vgg, progress)
        rows.append(("Baselines without learned prediction", method, result))
    text = table(rows, schedule, base, device, time.perf_counter() - t0)
    atomic_write_bytes(out / "table.md", text.encode())
    return text


def table(rows: list[tuple[str, str, dict]], schedule: TrainParams, base: ModelParams, device: str,
          wall_s: float) -> str:
    """Markdown in the Table 4 layout: blocks of variants, PSNR / SSIM / LPIPS (full and valid pixels)."""
    lines = [f"Validation split; schedule: {schedule.steps} steps, batch {schedule.batch_size}, {schedule.targets} "
             f"targets, lr {schedule.lr}; {base.resolution}x{base.resolution}, P = {base.padding}, encoder "
             f"{base.encoder.name}; device {device}; this run {wall_s / 60:.1f} min (finished parts read back).", ""]
    body, current = [], None
    for block, name, result in rows:
        if block != current and block:
            body.append([f"**{block}**", "", "", "", "", ""])
        current = block
        if "not_applicable" in result:
            body.append([name, "n/a", "", "", "", result["not_applicable"]])
            continue
        m = result["mean"]
        # a mean that was not computed (LPIPS without weights) or is undefined (no target with a valid pixel): n/a
        body.append([f"**{name}**" if not block else name, *(value_cell(m.get(k), d) for k, d in (
            ("psnr", 3), ("ssim", 4), ("lpips", 4), ("psnr_masked", 3), ("ssim_masked", 4)))])
    header = ["Variant", "PSNR ↑", "SSIM ↑", "LPIPS ↓", "PSNR (valid) ↑", "SSIM (valid) ↑"]
    return "\n".join(lines) + "\n" + markdown_table(header, body) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="dataset folder written by `scenesplat-stereo build`")
    p.add_argument("--out", type=Path, required=True, help="ablation folder (a sub-folder per variant; resumes)")
    p.add_argument("--only", nargs="+", help="only the variants whose names contain one of these words (the two "
                                             "baselines always run)")
    p.add_argument("--lpips-vgg", help="VGG16 ImageNet weights (default: torch's hub cache, else 1 - SSIM)")
    p.add_argument("--encoder-cache", type=Path, metavar="CACHE",
                   help="the encoder's outputs on --data (`sgmodel encode`), read by every variant's run")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_device_argument(p)
    add_model_arguments(p)
    add_train_arguments(p)


def run(args: argparse.Namespace) -> int:
    model, tp = params_from_args(args)
    print(ablate(model, tp, args.data, args.out, device_from_flag(args.device), args.lpips_vgg, args.only,
                 not args.no_progress, args.encoder_cache))
    return 0
