"""Editing built shards for tests: rewrite a shard's samples (``index.json`` kept in step, so that only the edit
is left to find), and empty the valid masks of some samples (data without a valid pixel)."""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import tarfile
from pathlib import Path

import numpy as np

from scenesplat_stereo.shards import webdataset as shards
from scenesplat_stereo.shards.encode import decode_image, encode_mask_png


def rewrite(out: Path, split: str, name: str, change) -> None:
    """Rewrite one shard with ``change(key, members) -> members`` and update index.json to match, so that
    only the damage itself is left to find."""
    path = out / split / name
    samples = [(k, change(k, dict(m))) for k, m in shards.iter_shard(path)]
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for key, members in samples:
            for suffix, data in members.items():
                info = tarfile.TarInfo(f"{key}.{suffix}")
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    path.write_bytes(buf.getvalue())
    index_path = out / split / "index.json"
    index = json.loads(index_path.read_text())
    entry = next(e for e in index["shards"] if e["name"] == name)
    entry["bytes"], entry["sha256"] = len(buf.getvalue()), hashlib.sha256(buf.getvalue()).hexdigest()
    index_path.write_text(json.dumps(index))


def empty_masks(key: str, members: dict[str, bytes]) -> dict[str, bytes]:
    """The sample with every ``mask_<jj>.png`` all zero (no valid pixel), same size; for ``rewrite``."""
    for name in [n for n in members if n.startswith("mask_")]:
        members[name] = encode_mask_png(np.zeros(decode_image(members[name], "png").shape[:2], bool))
    return members


def without_valid_pixels(data: Path, out: Path, splits=("train", "val"), keys: set[str] | None = None) -> Path:
    """A copy of the dataset ``data`` at ``out`` whose samples in ``splits`` (only those named in ``keys``, if
    given) have no valid pixel."""
    shutil.copytree(data, out)
    for split in splits:
        for shard in sorted((out / split).glob("shard-*.tar")):
            rewrite(out, split, shard.name, lambda k, m: empty_masks(k, m) if keys is None or k in keys else m)
    return out
