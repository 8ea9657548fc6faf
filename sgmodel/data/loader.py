"""Shards (SPEC section 5) -> training and validation batches (SPEC section 7, the Batch contract of
/work/contracts.md).

One sample: the ``<key>.json`` record (``protocol.SampleMeta``), the left/right JPEGs, each stored target's
JPEG and mask PNG, and ``left_depth.exr`` when present, decoded through OpenImageIO and brought to S x S by
``square_crop.SquareCrop`` (K moved with it). Targets: training draws ``targets`` (T = 4) of the stored
ones uniformly without replacement; validation keeps all stored targets in stored order (or the first
``targets`` when a number is given). ``target_viewmats`` = inverse(c2w_target) @ c2w_left maps points in
the left camera's frame (OpenCV, metres) into each target camera.

Streaming (``ShardStream``, a ``torch.utils.data.IterableDataset``): the order of samples is planned by
``sample_order`` from ``index.json`` and the shards are read sequentially with ``shards.iter_shard``.

Reproducible training order, the same on any number of GPUs and loader workers. Training reads one
global sequence of samples, a pure function of the seed (``sample_order.train_walk``: each epoch every
sample once, shards in a seeded order, a seeded shuffle buffer); the batch of global step k is its
positions k B .. k B + B - 1 for the global batch size B (``sample_order.batch_positions``), and the
targets of slot i of step k are drawn with ``numpy.random.default_rng([seed, k, i])``. Rank r of W takes
slots r B/W .. (r + 1) B/W - 1; DataLoader worker w of n makes the batches of steps start + w, start + w + n,
... (a DataLoader hands local batch j to worker j % n). So step k sees the same samples and targets with 1,
2 or 8 ranks and any number of workers, and a run resumed at step k (``start_step=k``) on another number of
GPUs sees exactly the batches k, k+1, ... of the uninterrupted run. Each worker walks every shard's tar
headers but reads the bytes of its own samples only (``shards.iter_shard(want=...)`` seeks past the rest).

Bad input raises ``DataError`` naming the file (and the JSON field, through ``SampleMetaError``).
"""

from __future__ import annotations

import atexit
import collections
import json
import os
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from scenesplat_stereo.shards.encode import decode_image
from scenesplat_stereo.shards.sample import SampleMeta, SampleMetaError
from scenesplat_stereo.shards.webdataset import INDEX_NAME, iter_shard
from sgmodel.data import sample_order
from sgmodel.data.square_crop import ImageTooSmall, SquareCrop

TRAIN_TARGETS = 4  # targets drawn per pair in training (paper section 4, SPEC section 7)
RESOLUTION = 256  # S (paper section 4, SPEC section 7)
SHUFFLE_BUFFER = 64  # samples held by each training stream's shuffle buffer (not from the paper)
DEPTH_MEMBER = "left_depth.exr"
RUN_SPLITS = ("train", "val")  # the splits a training run reads (and an encoder cache holds by default)


class DataError(ValueError):
    """A data folder, index, shard or sample that cannot be read into batches; names the file/field.
    ``flag``: the command-line flag that asked for what the data cannot give (None: the data is at fault)."""

    def __init__(self, message: str, flag: str | None = None) -> None:
        super().__init__(message)
        self.flag = flag


@dataclass(frozen=True)
class Shard:
    """One shard of a split: its path and the keys ``index.json`` lists for it, in file order."""

    path: Path
    keys: tuple[str, ...]


def read_split(root: Path, split: str) -> list[Shard]:
    """The shards of ``root/<split>`` from its ``index.json``; DataError for a missing folder, index or
    shard, a malformed index, a shard without samples, or an empty split."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: {'not a folder' if root.exists() else 'data folder does not exist'}")
    folder = root / split
    if not folder.is_dir():
        present = sorted(p.name for p in root.iterdir() if (p / INDEX_NAME).is_file())
        raise DataError(f"{folder}: split {split!r} does not exist (splits here: {present or 'none'})")
    index_path = folder / INDEX_NAME
    try:
        index = json.loads(index_path.read_text())
        entries = [(e["name"], e["keys"], e["num_samples"]) for e in index["shards"]]
    except FileNotFoundError:
        raise DataError(f"{index_path}: missing (not a built split)") from None
    except (ValueError, KeyError, TypeError) as e:
        raise DataError(f"{index_path}: malformed ({type(e).__name__}: {e})") from None
    out = []
    for name, keys, count in entries:
        path = folder / str(name)
        if not path.is_file():
            raise DataError(f"{path}: listed in {index_path} but missing")
        if not isinstance(keys, list) or not keys or len(keys) != count:
            raise DataError(f"{index_path}: shard {name}: 'keys' must list its {count} samples (got {keys!r:.80})")
        out.append(Shard(path, tuple(str(k) for k in keys)))
    if not out:
        raise DataError(f"{index_path}: split {split!r} is empty (no shards)")
    return out


def _decode(members: dict[str, bytes], name: str, source: str, shape: tuple[int, ...]) -> np.ndarray:
    if name not in members:
        raise DataError(f"{source}.{name}: member missing")
    try:
        img = decode_image(members[name], name.rsplit(".", 1)[1])
    except ValueError as e:
        raise DataError(f"{source}.{name}: {e}") from None
    if img.shape != shape:
        raise DataError(f"{source}.{name}: decoded shape {img.shape}, the sample's JSON (width, height) says {shape}")
    return img


def _chw(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))


def read_meta(key: str, members: dict[str, bytes], source: str) -> SampleMeta:
    """The sample's ``<key>.json`` record; DataError naming ``<source>:<key>.json`` (and the field)."""
    where = f"{source}:{key}"
    if "json" not in members:
        raise DataError(f"{where}.json: member missing")
    try:
        meta = SampleMeta.from_json(members["json"], f"{where}.json")
    except SampleMetaError as e:
        raise DataError(str(e)) from None
    if meta.key != key:
        raise DataError(f"{where}.json: field 'key' is {meta.key!r}, the tar member says {key!r}")
    return meta


def _crop(meta: SampleMeta, where: str, size: int) -> SquareCrop:
    try:
        return SquareCrop.plan(meta.width, meta.height, size)
    except ImageTooSmall as e:
        raise DataError(f"{where}.json: fields 'width', 'height': {e}", "--resolution") from None


def _rgb(members: dict[str, bytes], name: str, where: str, meta: SampleMeta, crop: SquareCrop) -> torch.Tensor:
    image = _decode(members, name, where, (meta.height, meta.width, 3))
    return _chw(crop.image(image.astype(np.float32) / 255.0))


def _pair(members: dict[str, bytes], where: str, meta: SampleMeta, crop: SquareCrop
          ) -> tuple[torch.Tensor, torch.Tensor]:
    return _rgb(members, "left.jpg", where, meta, crop), _rgb(members, "right.jpg", where, meta, crop)


def load_pair(key: str, members: dict[str, bytes], source: str, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The sample's (left, right) [3,S,S] in [0,1], exactly as ``load_sample`` gives them (the encoder's input)."""
    where, meta = f"{source}:{key}", read_meta(key, members, source)
    return _pair(members, where, meta, _crop(meta, where, size))


def load_sample(key: str, members: dict[str, bytes], source: str, size: int, targets: int | None = None,
                rng: np.random.Generator | None = None, encoded: tuple | None = None) -> dict:
    """One sample as tensors at ``size`` x ``size`` (the Batch fields without the batch axis).

    ``source`` names the shard (errors say ``<source>:<key>.<member>``). Targets: with ``rng``,
    ``targets`` of the stored ones drawn uniformly without replacement (``rng.choice``); without, the
    first ``targets`` in stored order (None: all). ``encoded``: the sample's frozen-encoder outputs read
    from an encoder cache, (disparity [1,S,S], [feature maps]), kept as ``encoder_disparity`` and
    ``encoder_features``. ``target_groups``: the picked targets' labels, when the record has them.
    """
    where, meta = f"{source}:{key}", read_meta(key, members, source)
    count = meta.num_targets if targets is None else targets
    if count > meta.num_targets:
        raise DataError(f"{where}.json: field 'targets': {meta.num_targets} stored, {count} asked for", "--targets")
    pick = rng.choice(meta.num_targets, count, replace=False) if rng is not None else np.arange(count)
    crop = _crop(meta, where, size)
    hw = (meta.height, meta.width)
    ids = [meta.target_ids[i] for i in pick]
    targets = torch.stack([_rgb(members, f"target_{j:02d}.jpg", where, meta, crop) for j in ids])
    masks = torch.stack([_chw(crop.nearest(_decode(members, f"mask_{j:02d}.png", where, hw + (1,))) >= 128)
                         for j in ids])
    K = crop.intrinsics(meta.K)
    viewmats = np.linalg.inv(meta.targets[pick]) @ meta.c2w_left
    left, right = _pair(members, where, meta, crop)
    out = {
        "left": left, "right": right,
        "K": torch.from_numpy(K).float(), "baseline": torch.tensor(meta.baseline, dtype=torch.float32),
        "targets": targets, "masks": masks,
        "target_viewmats": torch.from_numpy(viewmats).float(),
        "target_Ks": torch.from_numpy(np.repeat(K[None], len(ids), axis=0)).float(),
        "target_ids": torch.tensor(ids, dtype=torch.int64), "key": key, "scene": meta.scene,
    }
    if meta.target_groups is not None:
        out["target_groups"] = [meta.target_groups[i] for i in pick]
    if DEPTH_MEMBER in members:
        depth = _decode(members, DEPTH_MEMBER, where, hw + (1,)).astype(np.float32)
        if not (np.isfinite(depth).all() and (depth >= 0).all()):
            raise DataError(f"{where}.{DEPTH_MEMBER}: non-finite or negative depth")
        out["depth"] = _chw(crop.nearest(depth))
    if encoded is not None:
        out["encoder_disparity"], out["encoder_features"] = encoded
    return out


def collate(samples: list[dict]) -> dict:
    """Stack samples into the Batch dict (``keys``/``scenes`` as lists; ``target_groups`` a list per sample
    (its targets' labels, None for a sample without) when some sample has them; ``depth`` only when every sample
    has it; ``encoder_disparity`` [B,1,S,S] and ``encoder_features`` (a list, one [B,C_s,..] per scale) when
    they come from an encoder cache). DataError when the samples disagree in target count or in having depth."""
    if not samples:
        raise DataError("collate: no samples")
    keys = [s["key"] for s in samples]
    counts = {s["targets"].shape[0] for s in samples}
    if len(counts) > 1:
        raise DataError(f"samples {keys} have different numbers of targets {sorted(counts)}; "
                        "a batch needs the same T (give `targets`)")
    with_depth = ["depth" in s for s in samples]
    if any(with_depth) and not all(with_depth):
        raise DataError(f"samples {keys}: {DEPTH_MEMBER} in some but not all")
    tensors = ["left", "right", "K", "baseline", "targets", "masks", "target_viewmats", "target_Ks", "target_ids"]
    batch = {name: torch.stack([s[name] for s in samples]) for name in tensors + (["depth"] if all(with_depth) else [])}
    if any("encoder_disparity" in s for s in samples):
        batch["encoder_disparity"] = torch.stack([s["encoder_disparity"] for s in samples])
        batch["encoder_features"] = [torch.stack(maps) for maps in zip(*(s["encoder_features"] for s in samples))]
    batch["keys"], batch["scenes"] = keys, [s["scene"] for s in samples]
    if any("target_groups" in s for s in samples):
        batch["target_groups"] = [s.get("target_groups") for s in samples]
    return batch


#: the batches a loader worker keeps after handing them over (``KeptBatches``)
KEPT_BATCHES = 2


class KeptBatches:
    """``collate`` in a loader worker, which keeps its last ``KEPT_BATCHES`` batches. A batch's tensors reach
    the consuming process in shared memory, and whichever process drops a segment last frees its pages: for a
    cached training batch (264 MiB with float32 features) that took 35 ms of the dropping thread with the GIL
    held; in a CUDA run that thread is the pin-memory thread, and the main thread could queue no kernel meanwhile
    (docs/benchmarks.md "The loader's hand-over"). Kept here a little longer, the worker drops them last and
    frees them in its own process; the consumer's drop only unmaps (0.1 ms). Costs the host's memory for those
    batches, per worker; training's loader only (``make_loader``)."""

    def __init__(self) -> None:
        self._kept: collections.deque = collections.deque(maxlen=KEPT_BATCHES)

    def __call__(self, samples: list[dict]) -> dict:
        batch = collate(samples)
        self._kept.append(batch)
        return batch


def grouped_batches(samples: Iterable[dict], batch_size: int) -> Iterator[dict]:
    """Collate consecutive samples into batches of up to ``batch_size`` that share one number of targets
    (a sample may store any number: 10 rendered targets, or the real frames of StereoNVS and IRS)."""
    group: list[dict] = []
    for sample in samples:
        if group and (len(group) == batch_size or sample["targets"].shape[0] != group[0]["targets"].shape[0]):
            yield collate(group)
            group = []
        group.append(sample)
    if group:
        yield collate(group)


def eval_batches(root: Path, split: str, batch_size: int, resolution: int = RESOLUTION) -> Iterator[dict]:
    """One deterministic pass over ``root/<split>`` with every stored target, in batches of up to
    ``batch_size`` samples of equal target count (``grouped_batches``), in the main process."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    return grouped_batches(iter(ShardStream(root, split, resolution, None, train=False)), batch_size)


class ShardStream(IterableDataset):
    """Samples of ``root/<split>`` for one DDP rank (see the module docstring for order and resume).

    ``train``: endless, shuffled, ``targets`` (int) drawn per sample; else finite, deterministic, all
    stored targets (``targets`` None) or the first ``targets``. ``batch_size`` must be the DataLoader's
    (it numbers the steps that seed the target draws); ``start_step`` resumes a training run. ``cache``: an
    ``encoder_cache.EncoderCache`` of this data; each sample then carries its frozen-encoder outputs, read
    from the cache's shard of the same name in step with the data's.
    """

    def __init__(self, root: Path, split: str, resolution: int = RESOLUTION, targets: int | None = TRAIN_TARGETS,
                 seed: int = 0, train: bool = True, batch_size: int = 1, rank: int = 0, world_size: int = 1,
                 shuffle_buffer: int = SHUFFLE_BUFFER, start_step: int = 0, cache=None) -> None:
        super().__init__()
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} not in 0..{world_size - 1}")
        if train and (targets is None or targets < 1):
            raise ValueError(f"training needs a number of targets >= 1, got {targets}")
        if batch_size < 1 or resolution < 1 or start_step < 0:
            raise ValueError(f"batch_size {batch_size}, resolution {resolution}, start_step {start_step}")
        self.shards, self.split, self.cache = read_split(root, split), split, cache
        self.counts = [len(s.keys) for s in self.shards]
        self.resolution, self.targets, self.seed, self.train = resolution, targets, seed, train
        self.batch_size, self.rank, self.world_size = batch_size, rank, world_size
        self.shuffle_buffer, self.start_step = shuffle_buffer, start_step
        if train and batch_size * world_size > sum(self.counts):
            raise DataError(f"{self.shards[0].path.parent}: a batch of {batch_size * world_size} pairs over all ranks "
                            f"is larger than the {sum(self.counts)} samples of the split; use a smaller --batch-size")

    def __len__(self) -> int:
        """Samples in the split (all ranks together)."""
        return sum(self.counts)

    def _worker(self) -> tuple[int, int]:
        info = get_worker_info()
        return (0, 1) if info is None else (info.id, info.num_workers)

    def __iter__(self) -> Iterator[dict]:
        worker, workers = self._worker()
        if not self.train:
            items = sample_order.validation_items(self.counts, self.rank * workers + worker, self.world_size * workers)
            for key, members, source, encoded in self._read(items, list(range(len(items)))):
                yield load_sample(key, members, source, self.resolution, self.targets, encoded=encoded)
            return
        yield from self._training(worker, workers)

    def _slots(self, worker: int, workers: int) -> Iterator[tuple[int, int, int]]:
        """(global step, slot in the global batch, position in the global sequence) of every sample this
        worker makes, in the order the DataLoader batches them."""
        global_batch, first = self.batch_size * self.world_size, self.rank * self.batch_size
        step = self.start_step + worker
        while True:
            for slot, position in enumerate(sample_order.batch_positions(step, global_batch, first, self.batch_size),
                                            first):
                yield step, slot, position
            step += workers

    def _training(self, worker: int, workers: int) -> Iterator[dict]:
        """This worker's training samples (see the module docstring), epoch by epoch of the global sequence."""
        total = sum(self.counts)
        slots = self._slots(worker, workers)
        pending = next(slots)
        while True:
            epoch, wanted = pending[2] // total, []
            while pending[2] // total == epoch:
                wanted.append(pending)
                pending = next(slots)
            items, emit = sample_order.train_walk(self.counts, self.seed, epoch, self.shuffle_buffer)
            picks = [emit[position % total] for *_, position in wanted]
            for (key, members, source, encoded), (step, slot, _) in zip(self._read(items, picks), wanted):
                rng = np.random.default_rng([self.seed, step, slot])
                yield load_sample(key, members, source, self.resolution, self.targets, rng, encoded)

    def _read(self, items: list[sample_order.Item], emit: list[int]
              ) -> Iterator[tuple[str, dict[str, bytes], str, tuple | None]]:
        """Yield (key, members, shard name, encoder outputs or None) for ``items[emit[j]]``, j in order
        (distinct indices), reading shards in item order, the bytes of wanted samples only, and holding only
        what the emission order has not reached yet."""
        wanted = {items[q]: j for j, q in enumerate(emit)}
        held: dict[int, tuple] = {}
        nxt = 0
        by_shard: dict[int, list[int]] = {}
        for s, i in items:
            by_shard.setdefault(s, []).append(i)
        for s, indices in by_shard.items():
            if not any((s, i) in wanted for i in indices):
                continue
            shard, i = self.shards[s], -1
            want = lambda i, s=s: (s, i) in wanted  # noqa: E731
            cached = self.cache.samples(self.split, shard, want) if self.cache is not None else None
            for i, (key, members) in enumerate(iter_shard(shard.path, want=want)):
                if i >= len(shard.keys) or key != shard.keys[i]:
                    listed = shard.keys[i] if i < len(shard.keys) else "nothing more"
                    raise DataError(f"{shard.path}: sample {i} is {key!r}, index.json lists {listed!r}")
                encoded = next(cached) if cached is not None else None
                j = wanted.get((s, i))
                if j is not None:
                    held[j] = (key, members, str(shard.path), encoded)
                while nxt in held:
                    yield held.pop(nxt)
                    nxt += 1
            if i + 1 < len(shard.keys):
                raise DataError(f"{shard.path}: {i + 1} samples, index.json lists {len(shard.keys)}")
        if nxt != len(emit):
            raise DataError(f"{self.shards[0].path.parent}: samples listed in index.json were not found")


def check_first_sample(shards: list[Shard], load) -> None:
    """``load(key, members, source)`` on the first sample of a split's ``shards`` (a check before a command
    writes anything); DataError naming the file, prefixed with the flag that asked for what the data cannot
    give (``--data`` when the data is at fault)."""
    first = shards[0]
    key, members = next(iter_shard(first.path), (None, None))
    if key is None:
        raise DataError(f"{first.path}: no samples, index.json lists {len(first.keys)}")
    try:
        load(key, members, str(first.path))
    except DataError as e:
        raise DataError(f"{e.flag or '--data'}: {e}", e.flag) from None


def check_valid_pixels(root: Path, split: str) -> None:
    """Some target of ``root/<split>`` has a valid pixel: its masks (``mask_<jj>.png``) are read in stored order
    until one has (on good data the first does). DataError naming the split folder and its shards when every
    mask is empty: no masked metric is defined on such data, which says its depths were all invalid (or rho
    wrong) when it was built. Reads only."""
    shards = read_split(root, split)
    for shard in shards:
        for key, members in iter_shard(shard.path):
            meta = read_meta(key, members, str(shard.path))
            for j in meta.target_ids:
                if _decode(members, f"mask_{j:02d}.png", f"{shard.path}:{key}", (meta.height, meta.width, 1)).any():
                    return
    names = shards[0].path.name if len(shards) == 1 else f"{shards[0].path.name} to {shards[-1].path.name}"
    raise DataError(f"--data {Path(root) / split}: no target has a valid pixel (every mask_<jj>.png in {names} is "
                    f"empty), so nothing can be measured over valid pixels; rebuild the split (were its depths all "
                    f"invalid, or rho wrong?)")


def init_loader_worker(_: int) -> None:
    """A DataLoader worker's setup: one resize thread (the workers are the parallelism), an exit without
    Python's finalization (``_leave_at_exit``), and no traceback when Ctrl-C cuts a handle's hand-over
    (``_quiet_hang_ups``)."""
    cv2.setNumThreads(1)
    atexit.register(_leave_at_exit)
    sys.excepthook = _quiet_hang_ups


def _quiet_hang_ups(kind, value, tb) -> None:
    """``sys.excepthook`` of a loader worker, which prints every exception as Python does except one: a connection
    that ended in the thread handing this worker's shared-memory handles to the command
    (``multiprocessing.resource_sharer``, which reports its errors through this hook). On Ctrl-C the command, stopped
    in the middle of taking a batch's handle, hangs up in the handshake; the worker, which torch keeps running until
    it is shut down, then printed a traceback beside the command's one line."""
    files, at = [], tb
    while at is not None:
        files.append(at.tb_frame.f_code.co_filename)
        at = at.tb_next
    if issubclass(kind, (EOFError, OSError)) and any(f.endswith("resource_sharer.py") for f in files):
        return
    sys.__excepthook__(kind, value, tb)


def _leave_at_exit() -> None:
    """End a loader worker once Python starts to exit, before its finalization. There CPython (up to 3.13) ends
    daemon threads still running with ``pthread_exit``; the worker's queue feeder thread is often one, freeing the
    tensors of a batch it just sent, and a thread ended inside libtorch's tensor release aborts the process
    (std::terminate: "terminate called without an active exception"; "DataLoader worker ... is killed by signal:
    Aborted" in the trainer's log). At this point the worker has left torch's loop: the trainer took what it
    wanted or shut the worker down, so nothing is lost."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def loader_workers(workers: int | None, local_ranks: int = 1) -> int:
    """DataLoader workers per rank: ``workers`` when given, else this host's CPUs (those this process may
    run on) shared among its ``local_ranks`` ranks, one left to each rank's own process, at most 8."""
    if workers is not None:
        return workers
    return max(1, min(8, len(os.sched_getaffinity(0)) // max(local_ranks, 1) - 1))


def make_loader(root: Path, split: str, batch_size: int, resolution: int = RESOLUTION,
                targets: int | None = TRAIN_TARGETS, seed: int = 0, num_workers: int = 0, rank: int = 0,
                world_size: int = 1, train: bool = True, start_step: int = 0,
                shuffle_buffer: int = SHUFFLE_BUFFER, cache=None, pin_memory: bool = False) -> DataLoader:
    """A DataLoader of Batch dicts over ``root/<split>`` for one rank: endless and reproducible from
    (seed, step) when ``train``, else one pass over this rank's share of the samples (validation: pass
    ``targets=None`` for all stored targets). ``cache``: an ``encoder_cache.EncoderCache`` of ``root``,
    whose encoder outputs then come with every sample. ``pin_memory``: batches in page-locked memory (for
    a CUDA consumer: its copies to the GPU then run asynchronously)."""
    dataset = ShardStream(root, split, resolution, targets, seed, train, batch_size, rank, world_size,
                          shuffle_buffer, start_step, cache)
    # Workers are spawned, not forked: a fork after the parent has used OpenImageIO (contact sheets) or
    # CUDA inherits their locked thread pools, and the workers hang at their first decode.
    workers = dict(worker_init_fn=init_loader_worker, multiprocessing_context="spawn",
                   persistent_workers=not train) if num_workers > 0 else {}
    # training's workers keep their last batches (``KeptBatches``); validation's, persistent, would keep them all run
    kept = num_workers > 0 and train
    return DataLoader(dataset, batch_size=batch_size, collate_fn=KeptBatches() if kept else collate,
                      num_workers=num_workers, pin_memory=pin_memory, **workers)


def batch_share(batch: dict, index: int, shares: int) -> dict:
    """Share ``index`` of ``shares`` equal shares of a Batch dict: its samples ``index * B/shares`` to
    ``(index + 1) * B/shares - 1`` in every per-sample value (tensors, the lists ``keys``, ``scenes`` and
    ``target_groups``, and each scale of ``encoder_features``): the slots rank ``index`` of ``shares`` would
    read (module docstring). ``shares`` must divide B."""
    n, rem = divmod(len(batch["keys"]), shares)
    if rem:
        raise ValueError(f"a batch of {len(batch['keys'])} pairs does not split into {shares} equal shares")
    part = slice(index * n, (index + 1) * n)

    def cut(name: str, v):
        if name == "encoder_features":  # a list of scales, each batched
            return [t[part] for t in v]
        return v[part] if torch.is_tensor(v) or isinstance(v, list) else v
    return {k: cut(k, v) for k, v in batch.items()}


def map_tensors(batch: dict, fn) -> dict:
    """The batch with ``fn`` applied to each of its tensors (and to each tensor of a list of them, as
    ``encoder_features``); other values as they are."""
    def apply(v):
        if torch.is_tensor(v):
            return fn(v)
        return [apply(x) for x in v] if isinstance(v, list) and v and torch.is_tensor(v[0]) else v
    return {k: apply(v) for k, v in batch.items()}


def to_device(batch: dict, device: torch.device) -> dict:
    """The batch's tensors (and lists of tensors) on ``device``; other values as they are."""
    return map_tensors(batch, lambda t: t.to(device, non_blocking=True))
