"""The flags several ``sgmodel`` commands share, and how they become parameters.

``add_model_arguments`` / ``add_train_arguments`` add the flags of ``ModelParams`` / ``TrainParams`` (used
by ``train``, ``ablate``, ``bench train``, ``bench predict``); ``params_from_args`` merges dataclass
defaults, the ``--preset`` and the flags given, and checks the result (a ValueError naming the flag);
``add_device_argument`` / ``device_from_flag`` give every command the same ``--device`` (checked when
parsed: cpu, cuda or cuda:N with that GPU present). Every number is checked by its argparse type (finite,
in range), so a refused value names its flag before any command starts. The command line
(``sgmodel.cli``) and the benchmarks (``sgmodel.bench``) both import this module, never each other.
"""

from __future__ import annotations

import argparse
import logging

import torch

from scenesplat_stereo.common.text import argtype, non_negative_number, open_fraction, positive_number, whole_number
from scenesplat_stereo.raster import check_device
from sgmodel.config import MAX_SEED, PRESETS, ModelParams, TrainParams
from sgmodel.encoders.flags import add_encoder_arguments, encoder_params

log = logging.getLogger(__name__)


def add_precision_argument(p: argparse.ArgumentParser) -> None:
    """``--amp`` of the commands that run a trained model (predict, eval, bench predict): bf16 autocast on CUDA
    instead of float32, the inference default (docs/benchmarks.md "bf16 or float32 at inference": the shipped
    model scores 0.86 dB lower in bf16 on the Middlebury photographs, and one pair is no faster)."""
    p.add_argument("--amp", action="store_true",
                   help="bf16 autocast on CUDA (default float32: as fast for one pair, 0.86 dB better on real "
                        "photographs; docs/benchmarks.md)")


def add_model_arguments(p: argparse.ArgumentParser) -> None:
    """Flags of ModelParams (defaults: the paper's, or the --preset's). Shared by train, ablate, bench."""
    g = p.add_argument_group("model (defaults: the paper's values, or the preset's)")
    g.add_argument("--preset", choices=sorted(PRESETS), default="paper",
                   help="'paper' (default): the paper's sizes and schedule; 'cpu-small': 64x64, padding 4, "
                        "32-channel decoder/predictor, sgbm encoder, batch 4, 2 targets, 200 steps (minutes on 2 "
                        "CPU cores)")
    add_encoder_arguments(g, "the preset's: psmnet-kitti, or sgbm with cpu-small")
    g.add_argument("--resolution", type=whole_number("--resolution", 16),
                   help="S: square input and target size, pixels (default 256)")
    g.add_argument("--padding", type=whole_number("--padding", 0),
                   help="P: canvas padding per side, pixels (default 16)")
    g.add_argument("--decoder-channels", type=whole_number("--decoder-channels"),
                   help="DPT descriptor width (default 128)")
    g.add_argument("--predictor-channels", type=whole_number("--predictor-channels"),
                   help="predictor width (default 128)")
    g.add_argument("--no-back-layer", action="store_true", help="ablation: front layer only")
    g.add_argument("--no-descriptor", action="store_true", help="ablation: no DPT descriptor in the predictor")
    g.add_argument("--no-rgbd", action="store_true", help="ablation: no RGB-D in the decoder and predictor inputs")
    g.add_argument("--no-composer", action="store_true",
                   help="ablation: plain activations instead of residual composition (docs/model.md)")
    g.add_argument("--edge-mask", choices=("none", "hard", "soft"), help="ablation: back-layer opacity gate")


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    """Flags of TrainParams (defaults: the paper's schedule, or the --preset's)."""
    g = p.add_argument_group("training (defaults: the paper's values, or the preset's)")
    g.add_argument("--steps", type=whole_number("--steps"), help="optimiser steps (default 30000)")
    g.add_argument("--batch-size", type=whole_number("--batch-size"),
                   help="stereo pairs per step over all ranks (default 32)")
    g.add_argument("--accumulate", type=whole_number("--accumulate"), metavar="N",
                   help="compute each rank's batch in N equal shares, one after another, their gradients averaged: "
                        "the step N GPUs take, holding one share's activations at a time (default 1; N must "
                        "divide the batch per rank)")
    g.add_argument("--targets", type=whole_number("--targets"),
                   help="targets per pair per step, of the stored 10 (default 4)")
    g.add_argument("--lr", type=positive_number("--lr"), help="AdamW peak learning rate (default 4e-4)")
    g.add_argument("--weight-decay", type=non_negative_number("--weight-decay"),
                   help="AdamW weight decay (default 0.01)")
    g.add_argument("--warmup", type=open_fraction("--warmup"), help="OneCycleLR warm-up fraction, in (0, 1) "
                                                                    "(default 0.09)")
    g.add_argument("--lpips-weight", type=non_negative_number("--lpips-weight"),
                   help="weight of the LPIPS (or 1 - SSIM) term (default 0.05; 0: MSE alone)")
    g.add_argument("--val-every", type=whole_number("--val-every"), help="steps between validations (default 3000)")
    g.add_argument("--val-samples", type=whole_number("--val-samples"), help="cap on validation samples (default: all)")
    g.add_argument("--log-every", type=whole_number("--log-every"),
                   help="steps between metrics.jsonl records (default 10)")
    g.add_argument("--seed", type=whole_number("--seed", 0, MAX_SEED),
                   help="data order, target draws and initialisation (default 0)")
    g.add_argument("--workers", type=whole_number("--workers", 0),
                   help="DataLoader workers per rank (default: this host's CPUs shared among its ranks, one "
                        "left to each rank, at most 8)")
    g.add_argument("--no-amp", action="store_true", help="float32 convolutions on CUDA (default: bf16 autocast)")
    g.add_argument("--no-compile-lpips", action="store_true",
                   help="run the LPIPS term's VGG16 eagerly on CUDA (default: torch.compile, about 15 s once "
                        "per process for a step about 7%% faster)")
    g.add_argument("--ddp-bucket-mb", type=positive_number("--ddp-bucket-mb"),
                   help="several GPUs: DDP's gradient bucket size in MiB (default 25)")
    g.add_argument("--ddp-bf16-grads", action="store_true",
                   help="several GPUs: all-reduce the gradients in bfloat16 (half the bytes; a run of its own: "
                        "the averaged gradient is rounded to bf16)")
    g.add_argument("--profile", action="store_true",
                   help="write each rank's time per step phase (data, encoder, forward, backward, exposed "
                        "all-reduce, optimiser) and validation time into metrics.jsonl (CUDA events: no sync)")
    p.set_defaults(**{_TRAINING: True})


_TRAINING = "training_flags"  # set by add_train_arguments: the schedule flags are the user's, check them
_TRAIN_FLAGS = ("steps", "batch_size", "accumulate", "targets", "lr", "weight_decay", "warmup", "lpips_weight",
                "val_every", "val_samples", "log_every", "seed", "workers", "ddp_bucket_mb")


def params_from_args(args: argparse.Namespace) -> tuple[ModelParams, TrainParams]:
    """Dataclass defaults <- the preset <- flags the user gave; ValueError naming the flag for a model that
    cannot be built or (with ``add_train_arguments``' flags) a schedule that cannot run."""
    model, train = preset_params(args.preset)
    model.encoder = encoder_params(args, model.encoder)
    for name in ("resolution", "padding"):
        if getattr(args, name) is not None:
            setattr(model, name, getattr(args, name))
    if args.decoder_channels:
        model.decoder.channels = args.decoder_channels
    if args.predictor_channels:
        model.predictor.channels = args.predictor_channels
    model.composer.back_layer = not args.no_back_layer and model.composer.back_layer
    model.descriptor = not args.no_descriptor and model.descriptor
    model.rgbd = not args.no_rgbd and model.rgbd
    model.composer.composer = not args.no_composer and model.composer.composer
    if args.edge_mask:
        model.composer.edge_mask = args.edge_mask
    for name in _TRAIN_FLAGS:
        if getattr(args, name, None) is not None:
            setattr(train, name, getattr(args, name))
    if getattr(args, "no_amp", False):
        train.amp = False
    if getattr(args, "no_compile_lpips", False):
        train.compile_lpips = False
    train.ddp_bf16_grads = getattr(args, "ddp_bf16_grads", False) or train.ddp_bf16_grads
    train.profile = getattr(args, "profile", False) or train.profile
    train.betas = tuple(train.betas)
    model.validate()
    if getattr(args, _TRAINING, False):  # the benches reuse some names (--warmup: untimed runs) for themselves
        train.validate()
    if train.lpips_weight == 0:
        log.warning("--lpips-weight 0: the loss is the MSE alone (no LPIPS or 1 - SSIM term)")
    return model, train


def preset_params(name: str) -> tuple[ModelParams, TrainParams]:
    """The dataclass defaults with the preset ``name`` over them."""
    preset = PRESETS[name]
    return (ModelParams.from_dict(_merge(ModelParams().to_dict(), preset["model"])),
            TrainParams(**_merge(TrainParams().to_dict(), preset["train"])))


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) else v
    return out


def add_device_argument(p: argparse.ArgumentParser) -> None:
    """``--device``: cpu, cuda or cuda:N (that GPU present), checked when parsed; default cuda when available."""
    p.add_argument("--device", type=argtype(check_device, "--device"), default=None,
                   help="cpu, cuda or cuda:N (default: cuda when available)")


def device_from_flag(name: str | None) -> str:
    """``--device`` as parsed by ``add_device_argument``: None picks cuda when available, else cpu; a name is
    checked again (ValueError naming --device) for callers that did not parse it."""
    if name is None:
        return "cuda" if torch.cuda.is_available() else "cpu"
    return check_device(name, "--device")
