"""WebDataset shards of SceneSplat-Stereo samples (SPEC section 5): writing (atomic, deterministic),
reading, ``index.json`` and ``stats.json``.

Layout of an output folder ``OUT``::

    OUT/<split>/shard-000000.tar        # tar of samples; member "<key>.<suffix>", key "<scene>__<frame:06d>"
    OUT/<split>/.done/shard-000000.json # done marker: keys, size, sha256, per-scene counts of that shard
    OUT/<split>/index.json              # the shards with their sample counts and keys
    OUT/stats.json                      # per-subset counts of paper Table 6

A shard is streamed to a hidden temp file beside it and ``os.replace``'d into place when complete; its
done marker is written (atomically) after it. A shard counts as finished only when both exist and agree,
so a build killed at any moment leaves no partial shard that a rerun would keep. Tar headers are fixed
(mtime 0, uid/gid 0, no user names, mode 0644) and members are sorted by name within a sample, so the same
samples always give the same bytes. The members of one sample are contiguous, as WebDataset expects.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import tarfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from scenesplat_stereo.common.files import TMP_PREFIX as _TMP_PREFIX
from scenesplat_stereo.common.files import atomic_write_bytes, remove_temp_files

__all__ = ["atomic_write_bytes"]  # re-exported: the one atomic writer lives in scenesplat_stereo.common.files

SHARD_NAME = "shard-{:06d}.tar"
DONE_DIR = ".done"
INDEX_NAME = "index.json"
STATS_NAME = "stats.json"
_SHARD_RE = re.compile(r"^shard-(\d{6,})\.tar$")


def _json_bytes(obj: Any) -> bytes:
    return (json.dumps(obj, indent=1) + "\n").encode()


def shard_path(root: Path, split: str, number: int) -> Path:
    """``root/<split>/shard-<number:06d>.tar``."""
    return Path(root) / split / SHARD_NAME.format(number)


def shard_number(name: str) -> int:
    """The number of a shard named ``shard-<NNNNNN>.tar``; ValueError for another name."""
    match = _SHARD_RE.match(name)
    if match is None:
        raise ValueError(f"{name!r} is not a shard name ({SHARD_NAME.format(0)}, ...)")
    return int(match.group(1))


def done_path(root: Path, split: str, number: int) -> Path:
    """The done marker of a shard: ``root/<split>/.done/shard-<number:06d>.json``."""
    return Path(root) / split / DONE_DIR / SHARD_NAME.format(number).replace(".tar", ".json")


def _temp_path(root: Path, split: str, number: int) -> Path:
    return Path(root) / split / f"{_TMP_PREFIX}{SHARD_NAME.format(number)}"


def check_key(key: str) -> None:
    """A sample key must be non-empty, without '.', '/' or whitespace (WebDataset splits member names at
    the first '.' of the base name)."""
    if not key or re.search(r"[./\s]", key):
        raise ValueError(f"sample key {key!r}: must be non-empty, without '.', '/' or whitespace")


def read_done(root: Path, split: str, number: int) -> dict | None:
    """The done marker of shard ``number`` if the shard is finished (marker readable, tar present with
    the recorded size), else None."""
    marker, tar = done_path(root, split, number), shard_path(root, split, number)
    try:
        info = json.loads(marker.read_text())
        if tar.stat().st_size != info["bytes"]:
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return info


def remove_shard(root: Path, split: str, number: int) -> None:
    """Remove a shard, its marker and its temp file (marker first, so nothing half-removed looks done)."""
    for path in (done_path(root, split, number), shard_path(root, split, number), _temp_path(root, split, number)):
        path.unlink(missing_ok=True)


_COPY_BUFSIZE = 1 << 24  # bytes


class ShardWriter:
    """Writes samples into ``root/<split>/shard-<NNNNNN>.tar``, ``samples_per_shard`` per shard, numbered
    from ``first_shard``. Use as a context manager; ``add(key, members)`` takes member suffixes
    ("left.jpg", "target_03.jpg", "mask_03.png", "json", ...) mapped to bytes.

    Each shard is streamed to a temp file (a stale one from a killed run is removed first) and
    ``os.replace``'d into place when full or on ``close()``; its done marker follows. ``abort()`` throws
    the shard in progress away. As a context manager, a ``with`` block that ends normally closes and one
    that ends with an exception aborts. ``written`` lists the shard numbers completed.
    """

    def __init__(self, root: Path, split: str, samples_per_shard: int, first_shard: int = 0) -> None:
        if samples_per_shard < 1:
            raise ValueError(f"ShardWriter: samples_per_shard must be >= 1, got {samples_per_shard}")
        if not split or re.search(r"[./\s]", split):
            raise ValueError(f"ShardWriter: bad split name {split!r}")
        self.root, self.split = Path(root), split
        self.samples_per_shard, self.next_shard = samples_per_shard, first_shard
        self.written: list[int] = []
        self._tar: tarfile.TarFile | None = None
        self._file = None
        self._buffer: _SampleBuffer | None = None
        self._hash = None
        self._keys: list[str] = []
        self._scenes: dict[str, dict] = {}

    def _open(self) -> None:
        number = self.next_shard
        remove_shard(self.root, self.split, number)  # an unfinished earlier attempt, if any
        tmp = _temp_path(self.root, self.split, number)
        tmp.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(tmp, "wb")
        self._hash = hashlib.sha256()
        self._buffer = _SampleBuffer(self._file, self._hash)
        # members are copied in one piece (tarfile's default copies 16 KiB at a time)
        self._tar = tarfile.open(fileobj=self._buffer, mode="w", format=tarfile.PAX_FORMAT, copybufsize=_COPY_BUFSIZE)
        self._keys, self._scenes = [], {}

    def add(self, key: str, members: dict[str, bytes]) -> None:
        """Append one sample. Members are written sorted by suffix; a ``json`` member, when present, feeds
        the per-scene counts of the done marker (scene, subset, teacher_psnr, number of targets)."""
        check_key(key)
        if not members:
            raise ValueError(f"sample {key}: no members")
        if self._tar is None:
            self._open()
        if key in self._keys:
            raise ValueError(f"sample {key}: key already in shard {self.next_shard}")
        for suffix in members:  # all checked before any is added
            if not suffix or "/" in suffix or suffix.startswith("."):
                raise ValueError(f"sample {key}: bad member suffix {suffix!r}")
        for suffix in sorted(members):
            data = members[suffix]
            info = tarfile.TarInfo(f"{key}.{suffix}")
            info.size, info.mtime, info.mode = len(data), 0, 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            self._tar.addfile(info, io.BytesIO(data))
        self._buffer.flush()
        self._keys.append(key)
        if "json" in members:
            meta = json.loads(members["json"])
            scene = self._scenes.setdefault(
                meta["scene"], {"subset": meta["subset"], "teacher_psnr": meta["teacher_psnr"], "pairs": 0, "targets": 0}
            )
            scene["pairs"] += 1
            scene["targets"] += len(meta["targets"])
        if len(self._keys) >= self.samples_per_shard:
            self._finish()

    def _finish(self) -> None:
        number = self.next_shard
        self._tar.close()
        self._buffer.flush()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        tar = shard_path(self.root, self.split, number)
        os.replace(_temp_path(self.root, self.split, number), tar)
        marker = {
            "shard": tar.name,
            "split": self.split,
            "num_samples": len(self._keys),
            "bytes": tar.stat().st_size,
            "sha256": self._hash.hexdigest(),
            "keys": self._keys,
            "scenes": self._scenes,
        }
        atomic_write_bytes(done_path(self.root, self.split, number), _json_bytes(marker))
        self.written.append(number)
        self._tar = self._file = self._buffer = None
        self.next_shard += 1

    def close(self) -> None:
        """Finish the shard in progress (if any sample was added since the last one finished)."""
        if self._tar is not None:
            self._finish()

    def abort(self) -> None:
        """Throw the shard in progress away (its temp file is removed); finished shards stay."""
        if self._tar is not None:
            try:
                self._tar.close()
            except Exception:  # the shard is being thrown away; its close may fail for the same reason
                pass
            self._file.close()
            _temp_path(self.root, self.split, self.next_shard).unlink(missing_ok=True)
            self._tar = self._file = self._buffer = None

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class PlannedShards:
    """A sink ``(key, members)`` that writes samples into planned shards: ``chunks`` lists (shard number,
    keys), and each shard is written by its own ``ShardWriter`` as its keys arrive in order. A key out of
    plan raises. ``discard()`` drops the shard in progress; ``done`` and ``pairs`` count finished shards
    and their samples."""

    def __init__(self, root: Path, split: str, chunks: list[tuple[int, list[str]]]) -> None:
        self.root, self.split, self.chunks = Path(root), split, chunks
        self.index = self.count = self.done = self.pairs = 0
        self.writer: ShardWriter | None = None

    def __call__(self, key: str, members: dict[str, bytes]) -> None:
        number, keys = self.chunks[self.index]
        if key != keys[self.count]:
            raise RuntimeError(f"shard {number}: got sample {key}, planned {keys[self.count]}")
        if self.writer is None:
            self.writer = ShardWriter(self.root, self.split, len(keys), first_shard=number)
        self.writer.add(key, members)  # the writer finishes the shard by itself at its len(keys)-th sample
        self.count += 1
        if self.count == len(keys):
            self.writer, self.count, self.index = None, 0, self.index + 1
            self.done, self.pairs = self.done + 1, self.pairs + len(keys)

    def discard(self) -> None:
        if self.writer is not None:
            self.writer.abort()
            self.writer = None

    def finished(self) -> int:
        """Planned shards that are finished on disk (a done marker with their planned keys). After an interrupt this
        is the count to report: one can land after a writer's done marker and before ``done`` counts it."""
        return sum((read_done(self.root, self.split, number) or {}).get("keys") == keys for number, keys in self.chunks)


def remove_unplanned(root: Path, split: str, planned: set[int]) -> int:
    """Remove the temp files of killed runs and every shard of ``root/<split>`` whose number is not in
    ``planned`` (an earlier layout); returns the number of shards removed."""
    folder = Path(root) / split
    if not folder.is_dir():
        return 0
    remove_temp_files(folder)  # the shard folder and its .done markers
    numbers = {int(m.group(1)) for p in folder.glob("shard-*.tar") if (m := _SHARD_RE.match(p.name))}
    numbers |= {int(m.group(1)) for p in (folder / DONE_DIR).glob("shard-*.json")
                if (m := _SHARD_RE.match(p.name.replace(".json", ".tar")))}
    stale = sorted(numbers - set(planned))
    for n in stale:
        remove_shard(root, split, n)
    return len(stale)


class _SampleBuffer:
    """The tar's file object: collects what tarfile writes for one sample (headers, data, padding) and
    hands it to the file and the hash in one piece on ``flush``: one write and one hash update per sample
    instead of tarfile's three writes per member (the writer thread's time per 1752x1168 pair fell from
    12-13.6 to 8.8-9.5 ms on an H100 host; docs/benchmarks.md)."""

    def __init__(self, f, digest) -> None:
        self._f, self._digest = f, digest
        self._parts: list[bytes] = []
        self._offset = f.tell()

    def write(self, data: bytes) -> int:
        self._parts.append(data)
        self._offset += len(data)
        return len(data)

    def tell(self) -> int:
        return self._offset

    def flush(self) -> None:
        data = b"".join(self._parts)
        self._parts.clear()
        self._digest.update(data)
        self._f.write(data)


class ShardError(ValueError):
    """A shard that cannot be read: not a tar, truncated or corrupt; the message names the shard and the member."""


def iter_shard(path: Path, want: Callable[[int], bool] | None = None
               ) -> Iterator[tuple[str, dict[str, bytes] | None]]:
    """Samples of one tar in file order, grouped WebDataset-style: (key, {suffix: bytes}).

    The key is the member name up to the first '.' of its base name. ``want(i)`` False for the i-th sample
    (0-based): its members are not read (the reader seeks past them) and None is yielded in their place.
    Raises ``ShardError`` (a ValueError naming the file, and the member where it stopped) when a sample's
    members are not contiguous, or the tar is not one, truncated or corrupt.
    """
    seen: set[str] = set()
    key, members, index = None, {}, -1
    where = "its first member"
    try:
        with tarfile.open(path, "r") as tar:
            for info in tar:
                if not info.isfile():
                    continue
                base = info.name.rsplit("/", 1)[-1]
                if "." not in base:
                    raise ShardError(f"{path}: member {info.name!r} has no suffix")
                k, suffix = base.split(".", 1)
                if k != key:
                    if key is not None:
                        yield key, members
                    if k in seen:
                        raise ShardError(f"{path}: members of sample {k!r} are not contiguous")
                    seen.add(k)
                    index += 1
                    key, members = k, ({} if want is None or want(index) else None)
                where = f"member {info.name!r}"
                if members is not None:
                    members[suffix] = tar.extractfile(info).read()
                where = f"the member after {info.name!r}"
    except (tarfile.TarError, EOFError) as e:
        raise ShardError(f"{path}: {where}: truncated or corrupt tar ({e}); rebuild this shard") from None
    if key is not None:
        yield key, members


def finished_shards(root: Path, split: str) -> dict[int, dict]:
    """{shard number: done marker} of the finished shards of a split, in number order."""
    folder = Path(root) / split / DONE_DIR
    out = {}
    for marker in sorted(folder.glob("shard-*.json")) if folder.is_dir() else []:
        match = _SHARD_RE.match(marker.name.replace(".json", ".tar"))
        if match is None:
            continue
        number = int(match.group(1))
        info = read_done(root, split, number)
        if info is not None:
            out[number] = info
    return dict(sorted(out.items()))


def write_index(root: Path, split: str) -> dict:
    """Write ``root/<split>/index.json`` from the finished shards and return it:
    ``{"split", "num_shards", "num_samples", "shards": [{"name", "num_samples", "bytes", "sha256", "keys"}]}``."""
    shards = [
        {"name": info["shard"]} | {k: info[k] for k in ("num_samples", "bytes", "sha256", "keys")}
        for info in finished_shards(root, split).values()
    ]
    index = {
        "split": split,
        "num_shards": len(shards),
        "num_samples": sum(s["num_samples"] for s in shards),
        "shards": shards,
    }
    atomic_write_bytes(Path(root) / split / INDEX_NAME, _json_bytes(index))
    return index


def splits_present(root: Path) -> list[str]:
    """The split folders of ``root`` that hold at least one finished shard, sorted."""
    root = Path(root)
    return sorted(p.name for p in root.iterdir() if p.is_dir() and finished_shards(root, p.name)) if root.is_dir() else []


def collect_stats(root: Path) -> dict:
    """Per-subset counts of paper Table 6 from the done markers of every split under ``root``.

    Returns ``{"subsets": {subset: {"splits": {split: {"scenes", "pairs", "targets", "teacher_psnr"}},
    "teacher_psnr": mean over all its scenes}}, "total": {split: {"scenes", "pairs", "targets"}}}``;
    ``teacher_psnr`` is the mean over scenes with a PSNR (null when none has one), in dB.
    """
    scenes: dict[tuple[str, str, str], dict] = {}  # (subset, split, scene) -> counts
    for split in splits_present(root):
        for info in finished_shards(root, split).values():
            for scene, c in info["scenes"].items():
                acc = scenes.setdefault((c["subset"], split, scene), {"psnr": c["teacher_psnr"], "pairs": 0, "targets": 0})
                acc["pairs"] += c["pairs"]
                acc["targets"] += c["targets"]

    def mean(values: list) -> float | None:
        values = [v for v in values if v is not None]
        return round(float(np.mean(values)), 4) if values else None

    subsets: dict[str, dict] = {}
    total: dict[str, dict] = {}
    for (subset, split, scene), acc in sorted(scenes.items()):
        entry = subsets.setdefault(subset, {"splits": {}, "_psnr": {}})
        row = entry["splits"].setdefault(split, {"scenes": 0, "pairs": 0, "targets": 0, "_psnr": []})
        row["scenes"] += 1
        row["pairs"] += acc["pairs"]
        row["targets"] += acc["targets"]
        row["_psnr"].append(acc["psnr"])
        entry["_psnr"][scene] = acc["psnr"]
        tot = total.setdefault(split, {"scenes": 0, "pairs": 0, "targets": 0})
        for k in ("pairs", "targets"):
            tot[k] += acc[k]
        tot["scenes"] += 1
    for entry in subsets.values():
        for row in entry["splits"].values():
            row["teacher_psnr"] = mean(row.pop("_psnr"))
        entry["teacher_psnr"] = mean(list(entry.pop("_psnr").values()))
    return {"subsets": subsets, "total": total}


def write_stats(root: Path, stats: dict) -> None:
    """Write ``root/stats.json`` (atomically)."""
    atomic_write_bytes(Path(root) / STATS_NAME, _json_bytes(stats))
