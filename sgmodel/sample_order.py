"""Which samples a loader stream reads, in which order: pure functions of the shard sizes, the seed and
the epoch, computed from ``index.json`` without reading any shard.

A *stream* is one DataLoader worker of one DDP rank: stream ``rank * workers + worker`` of
``streams = world_size * workers``.

- Split: with at least as many shards as streams, stream i reads the shards ``order[i::streams]`` (all
  their samples); with fewer, every stream walks all shards in ``order`` and keeps the samples at
  positions ``p % streams == i`` of that walk, so no stream is starved.
- Training (endless): epoch e walks the shards in ``order = permutation(seed, e)`` (the same on every rank,
  so the split is disjoint), and a shuffle buffer of ``buffer`` samples, seeded by (seed, e, stream),
  reorders the walk. Emission order is therefore a pure function of (seed, epoch, stream), and the
  samples read ahead of emission never exceed the buffer.
- Validation: shards in index order, samples in file order, no shuffling; every sample exactly once
  over all streams.

An input item is ``(shard, sample)``: the shard's position in ``index.json`` and the sample's position in
that shard.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

Item = tuple[int, int]


def split_items(counts: Sequence[int], order: Sequence[int], stream: int, streams: int) -> list[Item]:
    """The items stream ``stream`` of ``streams`` reads, in read order, when shards are walked in
    ``order`` (``counts[s]`` samples in shard s)."""
    if not 0 <= stream < streams:
        raise ValueError(f"stream {stream} not in 0..{streams - 1}")
    if len(counts) >= streams:
        return [(s, i) for s in list(order)[stream::streams] for i in range(counts[s])]
    walk = [(s, i) for s in order for i in range(counts[s])]
    return walk[stream::streams]


def buffer_shuffle(n: int, size: int, rng: np.random.Generator) -> list[int]:
    """Emission order (a permutation of 0..n-1) of a shuffle buffer of ``size`` fed items 0..n-1 in order:
    once full, each arriving item replaces a uniformly drawn buffered one, which is emitted; at the end
    the rest is emitted in a random order. At most ``size`` items are held between reading and emission."""
    if size <= 1:
        return list(range(n))
    out, buf = [], []
    for p in range(n):
        if len(buf) < size:
            buf.append(p)
            continue
        j = int(rng.integers(len(buf)))
        out.append(buf[j])
        buf[j] = p
    out.extend(buf[j] for j in rng.permutation(len(buf)))
    return out


def shard_permutation(num_shards: int, seed: int, epoch: int) -> list[int]:
    """The shard walk of training epoch ``epoch`` (the same on every rank and worker)."""
    return [int(s) for s in np.random.default_rng([seed, epoch]).permutation(num_shards)]


def train_epoch(counts: Sequence[int], seed: int, epoch: int, stream: int, streams: int,
                buffer: int) -> tuple[list[Item], list[int]]:
    """(items in read order, emission order as indices into them) of one training epoch of a stream."""
    items = split_items(counts, shard_permutation(len(counts), seed, epoch), stream, streams)
    rng = np.random.default_rng([seed, epoch, stream, 1])  # 1: the buffer's stream of draws
    return items, buffer_shuffle(len(items), buffer, rng)


def validation_items(counts: Sequence[int], stream: int, streams: int) -> list[Item]:
    """The items of a validation stream, in index and file order."""
    return split_items(counts, range(len(counts)), stream, streams)


def resume_worker(start_step: int, worker: int, workers: int) -> tuple[int, int]:
    """(virtual worker, first local batch) of DataLoader worker ``worker`` when a run restarts at global
    step ``start_step``.

    A DataLoader hands batch k of an iterable dataset to worker k % workers, as that worker's batch
    k // workers. A restarted loader counts from 0 again, so its worker w plays the part that worker
    v = (w + start_step) % workers played, from v's batch number ceil((start_step - v) / workers) on.
    """
    virtual = (worker + start_step) % workers
    return virtual, max(0, -(-(start_step - virtual) // workers))
