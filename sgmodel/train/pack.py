"""``sgmodel pack``: a run's checkpoint as a weights-only model file to share or ship (no optimiser, scheduler or
RNG state; the floating-point weights in float32, bfloat16 or float16).

    sgmodel pack RUN/checkpoints/best.pt --out model.pt --dtype bf16

The file loads wherever a checkpoint is taken (``sgmodel predict``/``eval --checkpoint model.pt``); a run
cannot resume from it. OUT is written atomically, with a manifest beside it (``.written-by.<name>``): a model
file an earlier ``sgmodel pack`` wrote, unchanged, is replaced; any other file at OUT is refused before the
checkpoint is read (``scenesplat_stereo.common.ownership.OwnedFile``), as is OUT naming the checkpoint itself. The
model shipped in the package (``sgmodel weights list``) was made this way; docs/model_card.md says which dtype
and why.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scenesplat_stereo.common.ownership import OwnedFile, check_apart
from sgmodel.model.checkpoint import PACK_DTYPES, checkpoint_bytes, pack_checkpoint
from sgmodel.weights import sha256_file

OWNER = "sgmodel pack"  # recorded beside OUT: a later pack may replace the model file it wrote


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", type=Path, help="a checkpoint written by `sgmodel train` (e.g. RUN/checkpoints/best.pt)")
    p.add_argument("--out", type=Path, required=True, help="the model file to write (a file an earlier pack wrote is "
                   "replaced, any other refused)")
    p.add_argument("--dtype", choices=sorted(PACK_DTYPES), default="fp32",
                   help="dtype of the stored weights (default fp32; bf16 and fp16 halve the file)")


def run(args: argparse.Namespace) -> int:
    check_apart(args.out, "--out", {"CHECKPOINT": args.checkpoint})
    out = OwnedFile(args.out, "--out", OWNER)  # before the checkpoint is read
    packed = pack_checkpoint(args.checkpoint, args.dtype)
    path = out.write(checkpoint_bytes(packed))
    print(f"{args.out}: {path.stat().st_size / 2**20:.2f} MiB, {len(packed['model'])} tensors in {args.dtype}, step "
          f"{packed['step']}, sha256 {sha256_file(path)}")
    return 0
