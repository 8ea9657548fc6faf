"""Which samples a loader stream reads, in which order: pure functions of the shard sizes, the seed and
the epoch, computed from ``index.json`` without reading any shard.

- Training (endless): epoch e walks all shards in ``order = shard_permutation(seed, e)``, each shard's
  samples in file order, and one shuffle buffer of ``buffer`` samples, seeded by (seed, e), reorders the
  walk (``train_walk``). Concatenated over epochs this is one global sequence; global step k takes its
  batch of B samples from positions k B .. k B + B - 1 (``batch_positions``), so every sample is used once
  per epoch and the batch of step k depends on (seed, k, B) alone, not on how many ranks or loader workers
  share the work: rank r of W takes slots r B/W .. (r + 1) B/W - 1 of it.
- Validation: a *stream* is one DataLoader worker of one DDP rank (stream ``rank * workers + worker`` of
  ``streams = world_size * workers``). With at least as many shards as streams, stream i reads the shards
  ``order[i::streams]`` (all their samples); with fewer, every stream walks all shards in ``order`` and keeps
  the samples at positions ``p % streams == i`` of that walk. Shards in index order, samples in file order,
  no shuffling; every sample exactly once over all streams.

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


def train_walk(counts: Sequence[int], seed: int, epoch: int, buffer: int) -> tuple[list[Item], list[int]]:
    """(items in read order, emission order as indices into them) of training epoch ``epoch``: every
    shard in ``shard_permutation(seed, epoch)``, each in file order, through one shuffle buffer."""
    items = [(s, i) for s in shard_permutation(len(counts), seed, epoch) for i in range(counts[s])]
    rng = np.random.default_rng([seed, epoch, 1])  # 1: the buffer's stream of draws
    return items, buffer_shuffle(len(items), buffer, rng)


def batch_positions(step: int, batch_size: int, first_slot: int = 0, slots: int | None = None) -> range:
    """Positions in the global training sequence of slots ``first_slot .. first_slot + slots - 1`` of the
    batch of global step ``step`` (``batch_size`` samples over all ranks; all slots by default)."""
    slots = batch_size - first_slot if slots is None else slots
    if not (0 <= first_slot and first_slot + slots <= batch_size):
        raise ValueError(f"slots {first_slot}..{first_slot + slots - 1} not in a batch of {batch_size}")
    return range(step * batch_size + first_slot, step * batch_size + first_slot + slots)


def validation_items(counts: Sequence[int], stream: int, streams: int) -> list[Item]:
    """The items of a validation stream, in index and file order."""
    return split_items(counts, range(len(counts)), stream, streams)
