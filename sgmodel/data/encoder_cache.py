"""The encoder cache: the frozen encoder's outputs for every sample of a dataset, computed once by
``sgmodel encode`` and read by ``sgmodel train --encoder-cache`` (and ``ablate``, ``bench train``) in place of
running the encoder at every step.

The encoder is frozen and a sample's left/right images are the same every epoch (the square crop is fixed;
no augmentation), so its disparity and features are a function of the sample alone. Read from the cache,
a step computes the same numbers as one that runs the encoder: the disparity in float32, the features in
the dtype the decoder casts them to first (bfloat16 under the bf16 autocast of CUDA training, else
float32). What may differ is the encoder's own rounding: cuDNN picks its algorithms per batch shape, and
the cache is computed in batches of other samples than a training step's (below 1 bf16 ulp; measured in
docs/benchmarks.md).

Layout of a cache folder ``CACHE`` (one owner: this module)::

    CACHE/cache.json                  # what was cached (below); written before the first shard
    CACHE/<split>/shard-NNNNNN.tar    # one per shard of the data's split, same name, same keys, same order
    CACHE/<split>/.done/...           # done markers (``scenesplat_stereo.shards.webdataset``): a rerun resumes
    CACHE/<split>/index.json          # written when the split is complete

Members per sample (WebDataset style, ``<key>.<suffix>``): ``disparity.npy`` float32 [1,S,S] (pixels, left
reference, as ``EncoderOutput.disparity``), and ``feature_<i>.npy`` [C_i, ceil(S/s_i), ceil(S/s_i)] for each
of the encoder's feature maps, float32 or bfloat16 stored as its uint16 bit pattern (``precision``).

``cache.json``: ``format``, ``encoder`` (``name``, ``weights_sha256``: the frozen network that made it),
``resolution`` (S), ``precision`` ("bf16-autocast" or "float32": how the encoder ran and how the features
are stored), ``feature_channels``, ``feature_scales``, ``data`` (the dataset folder when made) and
``splits`` ({split: sha256 of the data's ``index.json``}: a rebuilt dataset does not match an old cache).
"""

from __future__ import annotations

import hashlib
import io
import math
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.common.files import FileFormatError, read_json
from scenesplat_stereo.shards.webdataset import INDEX_NAME, iter_shard
from sgmodel.data.loader import DataError, Shard, read_split

FORMAT = "sgmodel-encoder-cache/1"
MANIFEST = "cache.json"
DISPARITY = "disparity.npy"
BF16 = "bf16-autocast"  # the encoder ran under bf16 autocast on CUDA; features stored in bfloat16
PRECISIONS = (BF16, "float32")
FLAG = "--encoder-cache"


def precision_of(device: torch.device | str, amp: bool) -> str:
    """How the encoder runs in a training process: under bf16 autocast on CUDA with ``amp``, else float32."""
    return BF16 if amp and torch.device(device).type == "cuda" else "float32"


def feature_dtype(precision: str) -> torch.dtype:
    """The dtype features are stored in: bfloat16 for "bf16-autocast" (what the decoder casts them to), else float32."""
    return torch.bfloat16 if precision == BF16 else torch.float32


def feature_member(i: int) -> str:
    return f"feature_{i}.npy"


def index_sha256(data: Path, split: str) -> str:
    """sha256 of ``data/<split>/index.json`` (the identity of the split a cache was made from)."""
    return hashlib.sha256((Path(data) / split / INDEX_NAME).read_bytes()).hexdigest()


def manifest(encoder, resolution: int, precision: str, data: Path, splits: list[str]) -> dict:
    """``cache.json`` of a cache of ``encoder``'s outputs on ``data``'s ``splits`` at ``resolution``."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: one of {PRECISIONS}")
    return {"format": FORMAT, "encoder": {"name": encoder.name, "weights_sha256": encoder.weights_sha256},
            "resolution": resolution, "precision": precision, "feature_channels": list(encoder.feature_channels),
            "feature_scales": list(encoder.feature_scales), "data": str(Path(data).resolve()),
            "splits": {split: index_sha256(data, split) for split in splits}}


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return buffer.getvalue()


def sample_members(disparity: torch.Tensor, features: list[torch.Tensor], precision: str) -> dict[str, bytes]:
    """The members of one sample: ``disparity`` [1,S,S] and ``features`` [C_i,h_i,w_i] (any dtype/device) as
    stored (float32 disparity; features float32, or bfloat16 bits as uint16 for "bf16-autocast")."""
    members = {DISPARITY: _npy(disparity.detach().float().cpu().numpy())}
    for i, f in enumerate(features):
        f = f.detach().to(feature_dtype(precision)).cpu()
        members[feature_member(i)] = _npy((f.view(torch.uint16) if precision == BF16 else f).numpy())
    return members


class EncoderCache:
    """An opened, checked cache (``open_cache``): ``samples`` reads a shard's encoder outputs in step with
    the data's shard of the same name (``sgmodel.data.loader.ShardStream``)."""

    def __init__(self, root: Path, info: dict) -> None:
        self.root, self.info = Path(root), info
        self.precision = info["precision"]
        S = info["resolution"]
        self.shapes = [(1, S, S)] + [(c, math.ceil(S / s), math.ceil(S / s))
                                     for c, s in zip(info["feature_channels"], info["feature_scales"])]

    def samples(self, split: str, shard: Shard, want: Callable[[int], bool]
                ) -> Iterator[tuple[torch.Tensor, list[torch.Tensor]] | None]:
        """(disparity, features) of each sample of the data's ``shard`` in file order (None where ``want(i)``
        is False: its bytes are skipped); DataError naming the cache's shard and member when they do not
        fit."""
        path = self.root / split / shard.path.name
        count = 0
        for i, (key, members) in enumerate(iter_shard(path, want=want)):
            if i >= len(shard.keys) or key != shard.keys[i]:
                listed = shard.keys[i] if i < len(shard.keys) else "nothing more"
                raise DataError(f"{path}: sample {i} is {key!r}, the data's {shard.path.name} has {listed!r}; "
                                f"make the cache again (`sgmodel encode`)", FLAG)
            count += 1
            yield None if members is None else self.decode(members, f"{path}:{key}")
        if count != len(shard.keys):
            raise DataError(f"{path}: {count} samples, the data's {shard.path.name} has {len(shard.keys)}", FLAG)

    def decode(self, members: dict[str, bytes], where: str) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """One sample's members -> (disparity [1,S,S] float32, [feature maps])."""
        names = [DISPARITY] + [feature_member(i) for i in range(len(self.shapes) - 1)]
        arrays = []
        for n, (name, shape) in enumerate(zip(names, self.shapes)):
            if name not in members:
                raise DataError(f"{where}.{name}: member missing", FLAG)
            try:
                array = np.load(io.BytesIO(members[name]), allow_pickle=False)
            except ValueError as e:
                raise DataError(f"{where}.{name}: not a .npy array ({e})", FLAG) from None
            stored = np.uint16 if n > 0 and self.precision == BF16 else np.float32
            if array.shape != shape or array.dtype != stored:
                raise DataError(f"{where}.{name}: {array.dtype} {array.shape}, cache.json says "
                                f"{np.dtype(stored)} {shape}", FLAG)
            tensor = torch.from_numpy(array)
            arrays.append(tensor.view(torch.bfloat16) if stored == np.uint16 else tensor)
        if not torch.isfinite(arrays[0]).all():
            raise DataError(f"{where}.{DISPARITY}: non-finite disparity", FLAG)
        return arrays[0], arrays[1:]


def read_manifest(root: Path) -> dict:
    """``CACHE/cache.json`` parsed and its fields' types checked; DataError naming the file and field."""
    path = Path(root) / MANIFEST
    if not Path(root).is_dir():
        raise DataError(f"{FLAG} {root}: {'not a folder' if Path(root).exists() else 'does not exist'}", FLAG)
    if not path.is_file():
        raise DataError(f"{FLAG} {root}: not an encoder cache (no {MANIFEST}); make one with `sgmodel encode`", FLAG)
    try:
        info = read_json(path)
    except FileFormatError as e:
        raise DataError(str(e), FLAG) from None
    types = {"format": str, "encoder": dict, "resolution": int, "precision": str, "feature_channels": list,
             "feature_scales": list, "data": str, "splits": dict}
    for field, kind in types.items():
        if not isinstance(info, dict) or not isinstance(info.get(field), kind):
            raise DataError(f"{path}: field {field!r} missing or not a {kind.__name__}", FLAG)
    if info["format"] != FORMAT:
        raise DataError(f"{path}: field 'format' is {info['format']!r}, expected {FORMAT!r}", FLAG)
    if info["precision"] not in PRECISIONS:
        raise DataError(f"{path}: field 'precision' is {info['precision']!r}, expected one of {PRECISIONS}", FLAG)
    return info


def differences(found: dict, wanted: dict, splits: list[str]) -> list[str]:
    """The fields of cache.json ``found`` that do not match ``wanted`` (a ``manifest`` of the run), as
    'field: cache X, this run Y' (the data folder's path is not compared: a moved dataset still matches)."""
    out = []
    for field in ("encoder", "resolution", "precision", "feature_channels", "feature_scales"):
        if found[field] != wanted[field]:
            out.append(f"field {field!r}: the cache's {found[field]}, this run's {wanted[field]}")
    for split in splits:
        if split not in found["splits"]:
            out.append(f"field 'splits': no {split!r} split in the cache")
        elif found["splits"][split] != wanted["splits"][split]:
            out.append(f"field 'splits.{split}': made from another {split}/{INDEX_NAME} of the data (rebuilt since)")
    return out


def open_cache(root: Path, data: Path, encoder, resolution: int, precision: str, splits: list[str]) -> EncoderCache:
    """The cache at ``root``, checked against the run before anything is written: its cache.json matches the
    encoder (name and weights), the resolution, the precision and the data's splits, and every split is
    complete (its ``index.json`` lists the data's shards and keys, every shard of the recorded size).
    DataError naming ``--encoder-cache``, the file and the field otherwise."""
    root = Path(root)
    info = read_manifest(root)
    wanted = manifest(encoder, resolution, precision, data, splits)
    problems = differences(info, wanted, splits)
    if problems:
        raise DataError(f"{root / MANIFEST}: does not fit this run: {'; '.join(problems)}; make a cache for it "
                        f"with `sgmodel encode` (the same --encoder, --resolution and precision as the run)", FLAG)
    for split in splits:
        index_path = root / split / INDEX_NAME
        if not index_path.is_file():
            raise DataError(f"{index_path}: missing: the cache of split {split!r} is unfinished; rerun `sgmodel "
                            f"encode` with the same flags to complete it", FLAG)
        try:
            index = {s["name"]: s for s in read_json(index_path)["shards"]}
        except (FileFormatError, KeyError, TypeError) as e:
            raise DataError(f"{index_path}: malformed ({e})", FLAG) from None
        for shard in read_split(data, split):
            entry = index.get(shard.path.name)
            path = root / split / shard.path.name
            if entry is None or tuple(entry.get("keys", ())) != shard.keys:
                what = "missing" if entry is None else "of other keys"
                raise DataError(f"{index_path}: shard {shard.path.name} is {what}; rerun `sgmodel encode` with the "
                                f"same flags", FLAG)
            if not path.is_file() or path.stat().st_size != entry.get("bytes"):
                raise DataError(f"{path}: {'missing' if not path.is_file() else 'not the size index.json records'}"
                                f"; rerun `sgmodel encode` with the same flags", FLAG)
    return EncoderCache(root, info)
