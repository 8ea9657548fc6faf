"""How close the encoder cache's outputs are to the encoder run live on the same training batches (for
docs/benchmarks.md, "The encoder cache"). On the GPU, in bf16 autocast, with cuDNN's timed algorithm search
on as ``sgmodel train`` runs the encoder, each process may pick other algorithms, so a live encoder's
outputs differ between processes in their last bits; this measures the cache against the live encoder, and
(``--save-live`` in one process, ``--against-live`` in another) the live encoder against itself in another
process; ``--no-search`` runs the live encoder with cuDNN's default choice, as ``sgmodel encode`` does.
Prints a markdown table: per output, the largest and mean absolute difference, the largest relative to the
output's largest magnitude, and the share of elements that differ at all.

    python3 scripts/checks/gpu_cache_check.py --data DATA --cache CACHE [--batches 4] [--batch-size 32] [--no-search]
        [--save-live FILE | --against-live FILE]
"""

from __future__ import annotations

import argparse

import torch

from sgmodel.config import EncoderParams
from sgmodel.data.encoder_cache import open_cache, precision_of
from sgmodel.data.loader import make_loader, to_device
from sgmodel.encoders.flags import build_encoder
from sgmodel.model.layers import amp_autocast
from sgmodel.model.network import encode_pair


def compare(stats: dict, name: str, got: torch.Tensor, want: torch.Tensor) -> None:
    diff = (got.float() - want.float()).abs()
    row = stats.setdefault(name, [0.0, 0.0, 0, 0, 0.0])
    row[0] = max(row[0], float(diff.max()))
    row[1] += float(diff.sum())
    row[2] += int((diff > 0).sum())
    row[3] += diff.numel()
    row[4] = max(row[4], float(want.float().abs().max()))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True)
    p.add_argument("--cache", required=True)
    p.add_argument("--encoder", default="psmnet-kitti")
    p.add_argument("--resolution", type=int, default=256)
    p.add_argument("--batches", type=int, default=4)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--save-live", help="save this process's live outputs here")
    p.add_argument("--against-live", help="also compare with the live outputs another process saved here")
    p.add_argument("--no-search", action="store_true",
                   help="cuDNN's default algorithm choice, as `sgmodel encode` runs (default: its timed search, as "
                        "`sgmodel train` runs the encoder)")
    args = p.parse_args()
    device = torch.device("cuda")
    torch.backends.cudnn.benchmark = not args.no_search
    encoder = build_encoder(EncoderParams(name=args.encoder), device)
    cache = open_cache(args.cache, args.data, encoder, args.resolution, precision_of(device, True), ["train"])
    loader = make_loader(args.data, "train", args.batch_size, args.resolution, 4, num_workers=8, cache=cache,
                         pin_memory=True)
    other = torch.load(args.against_live) if args.against_live else None
    stats: dict[str, list] = {}
    saved = []
    batches = iter(loader)
    for b, batch in zip(range(args.batches), batches):
        batch = to_device(batch, device)
        with amp_autocast(batch["left"], True):
            disparity, features = encode_pair(encoder, batch["left"], batch["right"])
        live = [disparity] + [f.to(torch.bfloat16) for f in features]
        names = ["disparity (px)"] + [f"features at 1/{s}" for s in encoder.feature_scales]
        for name, got, want in zip(names, [batch["encoder_disparity"]] + batch["encoder_features"], live):
            compare(stats, f"cache vs live: {name}", got, want)
        if other is not None:
            for name, got, want in zip(names, [t.to(device) for t in other[b]], live):
                compare(stats, f"live vs live, another process: {name}", got, want)
        saved.append([t.cpu() for t in live])
    del batches  # the endless loader's workers stop here, not at interpreter exit
    if args.save_live:
        torch.save(saved, args.save_live)
    print(f"{args.batches} training batches of {args.batch_size} pairs, {args.encoder} at {args.resolution}, "
          f"bf16 autocast, cuDNN search {'off' if args.no_search else 'on'}, on {torch.cuda.get_device_name(device)}\n")
    print("| compared | max abs difference | mean abs difference | max / largest magnitude | elements that differ |")
    print("|---|---:|---:|---:|---:|")
    for name, (largest, total, differ, count, magnitude) in stats.items():
        print(f"| {name} | {largest:.3g} | {total / count:.3g} | {largest / magnitude:.2g} | {differ / count:.2%} |")


if __name__ == "__main__":
    main()
