"""What the composer keeps for its backward (issue 37): every storage its autograd graph saves, at the paper's
training shape (batch 32 of 256x256 pairs: a 288x288 canvas), with the branches laid out as the predictor gives
them (bf16 channels-last slices of 40 channels) and cast to float32 as ``StereoGaussians.compose`` casts them.

    python scripts/profile/composer_memory.py [--batch 32] [--canvas 288] [--out FILE]

It counts storages, not allocations, so the CPU gives the bytes the GPU keeps (the caching allocator rounds
each up a little). A saved view keeps its whole storage alive: the report names the storages that are the
float32 copies of the branches (37 channels, 375 MiB each at the paper's shape), which no saved tensor should
hold (``tests/sgmodel/model/test_composer.py``). The bytes are kept from the composer's forward until its backward,
so they count toward the training step's peak memory.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "checks"))

from compiled_composer import composed, inputs  # noqa: E402
from scenesplat_stereo.common.ownership import OwnedFile  # noqa: E402
from sgmodel.bench import report  # noqa: E402

MiB = 2**20


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--canvas", type=int, default=288, help="canvas pixels a side (256 + 2 x 16 for the paper model)")
    p.add_argument("--out", type=Path, help="also write the markdown report here")
    args = p.parse_args(argv)
    out = OwnedFile(args.out, "--out", "scripts/profile/composer_memory.py")
    B, S = args.batch, args.canvas
    front, back, dz, *rest = inputs(B, S, torch.device("cpu"))  # the predictor's layout (compiled_composer.py)
    front, back, dz = (t.requires_grad_() for t in (front, back, dz))
    front32, back32 = front.float(), back.float()  # as StereoGaussians.compose casts them (``composed`` copies no more)
    names = {front32.untyped_storage().data_ptr(): "the front branch in float32",
             back32.untyped_storage().data_ptr(): "the back branch in float32"}
    kept: dict[int, tuple[int, tuple[int, ...], str]] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        storage = t.untyped_storage()
        kept.setdefault(storage.data_ptr(), (storage.nbytes(), tuple(t.shape), names.get(storage.data_ptr(), "")))
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        result = composed(front32, back32, dz, *rest)
    outputs = sum(v.untyped_storage().nbytes() for v in result.values())
    total = sum(n for n, _, _ in kept.values())
    lines = [f"The composer's saved tensors for its backward, batch {B}, canvas {S}x{S}, torch {torch.__version__}: "
             f"**{total / MiB:.1f} MiB** in {len(kept)} storages (its outputs: {outputs / MiB:.1f} MiB).", "",
             "| storage, MiB | a tensor saved from it | what it is |", "|---:|---|---|"]
    for nbytes, shape, name in sorted(kept.values(), reverse=True)[:10]:
        lines.append(f"| {nbytes / MiB:.1f} | {list(shape)} | {name or 'made by the composer'} |")
    report("\n".join(lines) + "\n", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
