"""What the training loader's hand-over of a batch costs the consuming process, with and without the worker keeping
its last batches (``sgmodel.data.loader.KeptBatches``): the time to take a batch the workers have ready (its
shared-memory handles), the time to drop it (the last process to drop a segment frees its pages), and how much of
the main thread's Python work survives while another thread drops one (the pin-memory thread does, in a CUDA
run: a share near 1 means the drop left the GIL free). Host work only: runs on the CPU. Prints a markdown table
(medians of ``--repeats`` batches).

    python scripts/profile/loader_handover.py --data DATASET [--encoder-cache CACHE] [--workers 2] [--repeats 6]
        [--out FILE]

``--encoder-cache``: a cache made on this machine's CPU (float32 features), as ``sgmodel encode --device cpu``
makes it, for the batches of ``sgmodel train --encoder-cache``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from scenesplat_stereo.common.files import atomic_write_bytes  # noqa: E402
from scenesplat_stereo.common.text import markdown_table  # noqa: E402
from sgmodel.config import ModelParams  # noqa: E402
from sgmodel.data import loader  # noqa: E402
from sgmodel.data.encoder_cache import open_cache, precision_of  # noqa: E402
from sgmodel.model.network import create_model  # noqa: E402

#: seconds the workers get to have the next batch ready before it is taken
READY_S = 3.0
#: the window of the main thread's Python work, seconds
WINDOW_S = 0.1


def spin(seconds: float) -> int:
    """Iterations of a Python loop in ``seconds`` of wall time (a measure of the GIL this thread got)."""
    n, end = 0, time.perf_counter() + seconds
    while time.perf_counter() < end:
        n += 1
    return n


def measure(args, cache, kept: int) -> dict:
    """Medians over ``args.repeats`` batches with ``kept`` batches kept by each worker."""
    loader.KEPT_BATCHES = kept  # read when make_loader builds the workers' collate
    batches = iter(loader.make_loader(args.data, "train", args.batch_size, args.resolution, args.targets, 0,
                                      args.workers, cache=cache))
    tensors: list[torch.Tensor] = []
    loader.map_tensors(next(batches), tensors.append)
    size, count = sum(t.numel() * t.element_size() for t in tensors) / 2**20, len(tensors)
    del tensors
    take, drop, alone, beside = [], [], [], []
    for _ in range(args.repeats):
        time.sleep(READY_S)
        t0 = time.perf_counter()
        batch = next(batches)
        t1 = time.perf_counter()
        del batch
        take.append(t1 - t0)
        drop.append(time.perf_counter() - t1)
        time.sleep(READY_S)
        held = [next(batches)]
        alone.append(spin(WINDOW_S))
        dropper = threading.Thread(target=held.clear)
        dropper.start()
        beside.append(spin(WINDOW_S))
        dropper.join()
    return {"kept": kept, "MiB": size, "tensors": count, "take": statistics.median(take) * 1e3,
            "drop": statistics.median(drop) * 1e3, "share": statistics.median(b / a for a, b in zip(alone, beside))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--encoder-cache", type=Path)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--targets", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    cache = None
    if args.encoder_cache is not None:
        encoder = create_model(ModelParams(resolution=args.resolution)).encoder
        cache = open_cache(args.encoder_cache, args.data, encoder, args.resolution, precision_of("cpu", False),
                           ["train"])
    results = [measure(args, cache, kept) for kept in (0, loader.KEPT_BATCHES)]
    table = markdown_table(
        ["batches a worker keeps", "batch, MiB (tensors)", "take a ready batch, ms", "drop it, ms",
         "main thread's Python work while another thread drops one"],
        [[str(r["kept"]), f"{r['MiB']:.0f} ({r['tensors']})", f"{r['take']:.1f}", f"{r['drop']:.1f}",
          f"{100 * r['share']:.0f}%"] for r in results])
    text = (f"# The loader's hand-over of a batch: {args.batch_size} pairs at {args.resolution}x{args.resolution}, "
            f"{args.targets} targets{', encoder outputs from ' + str(args.encoder_cache) if cache else ''}; "
            f"{args.workers} workers; medians of {args.repeats} batches\n\n{table}\n")
    print(text)
    if args.out:
        atomic_write_bytes(args.out, text.encode())
    return 0

if __name__ == "__main__":
    sys.exit(main())
