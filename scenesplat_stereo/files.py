"""Atomic file output: every file this project writes appears whole or not at all.

The bytes go to a hidden temp file in the target's folder, are flushed and fsync'd, and are moved into
place with ``os.replace`` (atomic on POSIX within one file system); a failure at any step removes the
temp file and leaves an earlier file at ``path`` untouched. Permissions are the usual ``0666 & ~umask``.
``durable=False`` skips the fsync: the file still appears whole or not at all to every reader, but a power
loss soon after may leave it empty (for outputs that are cheap to make again, where the fsync would cost
more than the rest of the write: docs/benchmarks.md "Scene export").
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

TMP_PREFIX = ".tmp-"  # temp files of unfinished writes start with this (a rerun may remove them)


def atomic_write_bytes(path: str | os.PathLike, data: bytes | Sequence[Any], durable: bool = True) -> Path:
    """Write ``data`` (bytes, or a sequence of bytes-like objects such as contiguous numpy arrays, written in
    order without joining them) to ``path`` (parents created) through a temp file (fsync'd when ``durable``)
    and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f"{TMP_PREFIX}{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            for chunk in [data] if isinstance(data, (bytes, bytearray, memoryview)) else data:
                f.write(chunk)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1, sort_keys: bool = False) -> Path:
    """``obj`` as JSON text (``indent`` as in ``json.dumps``) plus a newline, written atomically."""
    return atomic_write_bytes(path, (json.dumps(obj, indent=indent, sort_keys=sort_keys) + "\n").encode())


def check_writable(folder: str | os.PathLike, flag: str) -> Path:
    """Create ``folder`` if needed and prove it writable with a temp file, before anything in it is
    removed; ValueError naming ``flag`` and the folder otherwise."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{flag} {folder}: exists and is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=TMP_PREFIX)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ValueError(f"{flag} {folder}: not writable ({e.strerror or e})") from None
    return folder
