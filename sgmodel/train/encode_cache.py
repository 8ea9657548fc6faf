"""``sgmodel encode``: run the frozen encoder once over a dataset and keep its outputs in an encoder cache
(``sgmodel.data.encoder_cache``), so ``sgmodel train --encoder-cache CACHE`` (and ``ablate``, ``bench train``) skip
the encoder at every step.

The encoder is frozen and every sample's input pair is the same each epoch, so this computes once what a
run would compute at every epoch: a step without the encoder (51 ms of 243 with PSMNet on an H100;
FoundationStereo costs far more), and one cache serves every run and every ablation variant on the same
data, encoder and resolution. Give the flags of the training runs it serves: ``--preset``, ``--encoder``
(``--encoder-weights``, ``--encoder-repo``), ``--resolution``, and ``--no-amp`` / ``--device cpu`` when the
runs use them (a run checks the cache's precision: bf16 autocast on CUDA, else float32). Size: about 2 MB a
pair for psmnet-kitti at 256x256 (its features at 1/2 and 1/4 in bf16).

Before anything is written: the flags, the data (each split's index and first pair at ``--resolution``),
the encoder and its weights, and ``--out`` (writable, apart from ``--data``, empty or a cache of the same
encoder, resolution and precision made from the same data). Shards are written whole (temp file, then
rename) with done markers; an interrupted or killed run resumes at the first unfinished shard, and
``CACHE/<split>/index.json`` marks a split complete. One process at a time writes ``--out`` (``.lock``).
Several GPUs: ``torchrun --nproc_per_node=N -m sgmodel.cli encode ...`` with the same flags; rank r encodes
every N-th shard of what is left (the same cache bytes as one process), rank 0 holds the lock and writes
``cache.json`` and the indexes.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from scenesplat_stereo.common.commandline import Interrupted
from scenesplat_stereo.common.files import atomic_write_json
from scenesplat_stereo.common.ownership import FolderLock, check_apart, check_replaceable
from scenesplat_stereo.common.text import format_table, whole_number
from scenesplat_stereo.shards.webdataset import (PlannedShards, iter_shard, read_done, remove_unplanned, shard_number,
                                                 write_index)
from sgmodel.args import add_device_argument, device_from_flag, preset_params
from sgmodel.config import PRESETS
from sgmodel.data import encoder_cache as cache_format
from sgmodel.data.loader import (RUN_SPLITS, DataError, Shard, check_first_sample, init_loader_worker, load_pair,
                                 read_split)
from sgmodel.encoders.flags import add_encoder_arguments, build_encoder, encoder_params
from sgmodel.model.layers import amp_autocast
from sgmodel.model.network import encode_pair
from sgmodel.train.distributed import World, all_sum, barrier, joined_world


OWNER = "sgmodel encode"  # a cache holds cache.json; any other --out must be new or empty


class PairChunks(Dataset):
    """Item j: up to a batch of consecutive pairs of one shard, ``(shard number, keys, left [n,3,S,S], right)``,
    decoded exactly as training decodes them (``data.load_pair``)."""

    def __init__(self, chunks: list[tuple[Shard, int, int]], size: int) -> None:
        self.chunks, self.size = chunks, size

    def __len__(self) -> int:
        return len(self.chunks)

    def __getitem__(self, j: int) -> tuple[int, list[str], torch.Tensor, torch.Tensor]:
        shard, first, end = self.chunks[j]
        keys, lefts, rights = [], [], []
        for i, (key, members) in enumerate(iter_shard(shard.path, want=lambda i: first <= i < end)):
            if members is None:
                continue
            if key != shard.keys[i]:
                raise DataError(f"{shard.path}: sample {i} is {key!r}, index.json lists {shard.keys[i]!r}")
            left, right = load_pair(key, members, str(shard.path), self.size)
            keys.append(key)
            lefts.append(left)
            rights.append(right)
        if len(keys) != end - first:
            raise DataError(f"{shard.path}: {len(keys)} of samples {first}..{end - 1} found, index.json lists "
                            f"{len(shard.keys)}")
        return shard_number(shard.path.name), keys, torch.stack(lefts), torch.stack(rights)


def check_data(data: Path, splits: list[str], size: int) -> dict[str, list[Shard]]:
    """Each split's shards (``data.read_split``), its shard names ours, and its first pair decoded at ``size``."""
    out = {}
    for split in splits:
        shards = read_split(data, split)
        for shard in shards:
            try:
                shard_number(shard.path.name)
            except ValueError as e:
                raise DataError(f"{shard.path}: {e}") from None
        check_first_sample(shards, lambda key, members, source: load_pair(key, members, source, size))
        out[split] = shards
    return out


def check_out(out: Path, data: Path, wanted: dict) -> dict:
    """``--out`` can take this cache (see the module docstring); the cache.json to write: ``wanted`` with the
    splits of an earlier cache kept. Reads only."""
    check_replaceable(out, "--out", OWNER, marker=cache_format.MANIFEST)  # new, empty, or a cache (cache.json)
    check_apart(out, "--out", {"--data": data})
    if not (out / cache_format.MANIFEST).is_file():
        return wanted
    try:
        found = cache_format.read_manifest(out)
    except DataError as e:
        raise ValueError(f"--out {out}: {e}") from None
    shared = [s for s in wanted["splits"] if s in found["splits"]]
    problems = cache_format.differences(found, wanted, shared)
    if problems:
        raise ValueError(f"--out {out}: holds an encoder cache of other settings ({'; '.join(problems)}); choose a "
                         f"new --out (or remove that one)")
    return {**wanted, "splits": {**found["splits"], **wanted["splits"]}}


def encode_dataset(data: Path, out: Path, encoder, size: int, precision: str, splits: list[str], device: str,
                   batch_size: int, workers: int, progress: bool = True, world: World | None = None) -> list[dict]:
    """Write (or complete) the cache of ``encoder`` on ``data``'s ``splits`` in ``out``; one summary row per split
    (counts summed over ranks; rank 0's rows also say the split's pairs and size). Under ``torchrun``
    (``world``) rank r encodes shards r, r + W, ... of what is left; rank 0 alone holds the lock and writes
    ``cache.json`` and the indexes."""
    data, out = Path(data), Path(out)
    world = world or World(0, 1, torch.device(device))
    shards = check_data(data, splits, size)
    info = check_out(out, data, cache_format.manifest(encoder, size, precision, data, splits))
    lock = FolderLock(out, "--out", OWNER)
    if world.main:
        lock.acquire()
    try:
        if world.main:
            atomic_write_json(out / cache_format.MANIFEST, info)
            for split in splits:
                remove_unplanned(out, split, {shard_number(s.path.name) for s in shards[split]})  # temp files
        barrier(world)
        # every rank plans before any writes, so all ranks see the same work left
        todo = {split: [s for s in shards[split] if (read_done(out, split, shard_number(s.path.name)) or {})
                        .get("keys") != list(s.keys)] for split in splits}
        rows = []
        for split in splits:
            t0 = time.perf_counter()
            mine = todo[split][world.rank::world.size]
            encoded = _encode_shards(out, encoder, size, precision, split, mine, device, batch_size, workers,
                                     progress and world.main)
            made, encoded = all_sum(world, [float(len(mine)), float(encoded)])
            rows.append({"split": split, "shards": len(shards[split]), "made": int(made), "encoded": int(encoded),
                         "s": time.perf_counter() - t0})
        barrier(world)
        for row in rows if world.main else []:  # rank 0 writes the indexes and reports
            index = write_index(out, row["split"])
            row.update(pairs=index["num_samples"], MB=sum(s["bytes"] for s in index["shards"]) / 1e6,
                       **{"pairs/s": row["encoded"] / row["s"] if row["encoded"] else float("nan")})
        return rows
    finally:
        lock.release()


def _encode_shards(out: Path, encoder, size: int, precision: str, split: str, todo: list[Shard], device: str,
                   batch_size: int, workers: int, progress: bool) -> int:
    """Encode the shards ``todo`` of ``split`` into ``out``; the number of pairs encoded."""
    chunks = [(s, i, min(i + batch_size, len(s.keys))) for s in todo for i in range(0, len(s.keys), batch_size)]
    sink = PlannedShards(out, split, [(shard_number(s.path.name), list(s.keys)) for s in todo])
    loader = DataLoader(PairChunks(chunks, size), batch_size=None, num_workers=workers,
                        **(dict(worker_init_fn=init_loader_worker, multiprocessing_context="spawn") if workers else {}))
    pairs = sum(len(s.keys) for s in todo)
    bar = tqdm(total=pairs, disable=not progress, unit="pair", desc=split, dynamic_ncols=True)
    try:
        for _, keys, left, right in loader:
            left, right = left.to(device, non_blocking=True), right.to(device, non_blocking=True)
            with amp_autocast(left, precision == cache_format.BF16):
                disparity, features = encode_pair(encoder, left, right)
            # to the host once per batch, in the stored dtypes (not one copy per sample and map)
            disparity = disparity.cpu()
            features = [f.to(cache_format.feature_dtype(precision)).cpu() for f in features]
            for b, key in enumerate(keys):
                sink(key, cache_format.sample_members(disparity[b], [f[b] for f in features], precision))
            bar.update(len(keys))
            bar.set_postfix(shards=f"{sink.done}/{len(todo)}")
    except KeyboardInterrupt:
        sink.discard()
        bar.close()
        raise Interrupted(f"{sink.finished()} of {len(todo)} {split} shards written this run; rerun the same command "
                          f"to resume") from None
    except BaseException:
        sink.discard()
        raise
    bar.close()
    return pairs


def summary(rows: list[dict], out: Path, ranks: int = 1) -> str:
    table = format_table([["split", "shards", "made now", "pairs", "encoded now", "MB", "s", "pairs/s"]] +
                         [[r["split"], r["shards"], r["made"], r["pairs"], r["encoded"], f"{r['MB']:.1f}",
                           f"{r['s']:.1f}", f"{r['pairs/s']:.1f}"] for r in rows], rule=True)
    return (f"{table}\n{ranks} rank(s); encoder cache in {out}: sgmodel train (or ablate) --encoder-cache {out} "
            f"with the same flags")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="dataset folder written by `scenesplat-stereo build`")
    p.add_argument("--out", type=Path, required=True, help="cache folder (created; an unfinished cache resumes)")
    p.add_argument("--splits", nargs="+", default=list(RUN_SPLITS), help="splits to cache (default: train val)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper",
                   help="the training runs' preset: its encoder and resolution are the defaults")
    add_encoder_arguments(p, "the preset's: psmnet-kitti, or sgbm with cpu-small")
    p.add_argument("--resolution", type=whole_number("--resolution", 16),
                   help="S of the training runs (default: the preset's, 256)")
    p.add_argument("--batch-size", type=whole_number("--batch-size"), default=32,
                   help="pairs per encoder call (default 32; the outputs do not depend on it)")
    p.add_argument("--workers", type=whole_number("--workers", 0), default=4,
                   help="processes decoding the pairs (default 4)")
    p.add_argument("--no-amp", action="store_true",
                   help="run the encoder in float32 on CUDA, for runs trained with --no-amp (default: bf16 autocast)")
    add_device_argument(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    model, _ = preset_params(args.preset)
    params = encoder_params(args, model.encoder)
    size = args.resolution or model.resolution
    splits = list(dict.fromkeys(args.splits))
    with joined_world(device_from_flag(args.device)) as world:
        # cuDNN's default algorithm choice, not `train`'s timed search: the same cache bytes on every run and resume
        torch.backends.cudnn.benchmark = False
        encoder = build_encoder(params, world.device)
        precision = cache_format.precision_of(world.device, not args.no_amp)
        rows = encode_dataset(args.data, args.out, encoder, size, precision, splits, str(world.device),
                              args.batch_size, args.workers, not args.no_progress, world)
        if world.main:
            print(summary(rows, args.out, world.size))
        return 0
