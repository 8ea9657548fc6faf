"""``sgmodel pack``: a run's checkpoint as a weights-only model file to share or ship (no optimiser, scheduler or
RNG state; the floating-point weights in float32, bfloat16 or float16).

    sgmodel pack RUN/checkpoints/best.pt --out model.pt --dtype bf16

The file loads wherever a checkpoint is taken (``sgmodel predict``/``eval --checkpoint model.pt``); a run
cannot resume from it. OUT must not exist (nothing is replaced) and is written atomically. The model shipped
in the package (``sgmodel weights list``) was made this way; docs/model_card.md says which dtype and why.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sgmodel.model.checkpoint import PACK_DTYPES, pack_checkpoint
from sgmodel.weights import sha256_file


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", type=Path, help="a checkpoint written by `sgmodel train` (e.g. RUN/checkpoints/best.pt)")
    p.add_argument("--out", type=Path, required=True, help="the model file to write (must not exist)")
    p.add_argument("--dtype", choices=sorted(PACK_DTYPES), default="fp32",
                   help="dtype of the stored weights (default fp32; bf16 and fp16 halve the file)")


def run(args: argparse.Namespace) -> int:
    if args.out.exists() or args.out.is_symlink():
        raise ValueError(f"--out {args.out}: exists; choose a new file (nothing is replaced)")
    if not args.out.parent.is_dir():
        raise ValueError(f"--out {args.out}: its folder {args.out.parent} does not exist")
    packed = pack_checkpoint(args.checkpoint, args.out, args.dtype)
    size = args.out.stat().st_size
    print(f"{args.out}: {size / 2**20:.2f} MiB, {len(packed['model'])} tensors in {args.dtype}, step "
          f"{packed['step']}, sha256 {sha256_file(args.out)}")
    return 0
