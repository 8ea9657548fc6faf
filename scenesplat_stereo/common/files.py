"""Files this project writes: every one appears whole or not at all.

* ``atomic_write_bytes`` / ``atomic_write_json``: the bytes go to a hidden temp file in the target's
  folder, are flushed and fsync'd, and are moved into place with ``os.replace`` (atomic on POSIX within one
  file system); a failure at any step removes the temp file and leaves an earlier file untouched.
  Permissions are the usual ``0666 & ~umask``. ``durable=False`` skips the fsync: the file still appears
  whole or not at all to every reader, but a power loss soon after may leave it empty (for outputs that are
  cheap to make again, where the fsync would cost more than the rest of the write: docs/benchmarks.md
  "Scene export"). Temp files start with ``TMP_PREFIX``; ``remove_temp_files`` sweeps those a killed process
  left.
* ``append_line`` appends one whole line to a log (JSON lines) or none: a failed write is cut back off.
  ``read_json_lines`` reads such a log back, dropping a torn last line (a crash mid-write).
* ``read_json``: JSON that does not parse is a ``FileFormatError`` naming the file, line and column.

Whether a command may replace what is at its output, and one writer per folder: ``common.ownership``.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

TMP_PREFIX = ".tmp-"  # temp files and folders of unfinished writes start with this (a rerun may remove them)
log = logging.getLogger(__name__)


class FileFormatError(ValueError):
    """A file that cannot be read as what it should be; the message names the file and the place."""


def atomic_write_bytes(path: str | os.PathLike, data: bytes | Iterable[Any], durable: bool = True) -> Path:
    """Write ``data`` (bytes, or an iterable of bytes-like objects such as contiguous numpy arrays, written in
    order as it gives them, without joining them: a generator may wait for each part) to ``path`` (parents
    created) through a temp file (fsync'd when ``durable``) and ``os.replace``. An error while writing, the
    iterable's included, leaves ``path`` as it was."""
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


def read_json(path: str | os.PathLike) -> Any:
    """The JSON document in ``path``; ``FileFormatError`` naming the file (and line and column) when it does
    not parse or is not UTF-8. OSErrors (a missing file) pass through with the file named."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise FileFormatError(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except UnicodeDecodeError as e:
        raise FileFormatError(f"{path}: not UTF-8 text (byte {e.start})") from None


def append_line(path: str | os.PathLike, text: str) -> None:
    """Append ``text`` and a newline to ``path`` (created) in one write; if the write fails or is short
    (a full disk), the file is cut back to its earlier length, so it only ever holds whole lines."""
    data = (text.rstrip("\n") + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        size = os.fstat(fd).st_size
        try:
            if os.write(fd, data) != len(data):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        except BaseException:
            os.ftruncate(fd, size)
            raise
    finally:
        os.close(fd)


def read_json_lines(path: str | os.PathLike) -> list[dict]:
    """The records of a JSON-lines log written by ``append_line``. A torn last line (not JSON: the writer
    was killed mid-write) is dropped with a warning naming the file; a bad line before the last is a
    ``FileFormatError`` naming the file and the line. [] when the file does not exist."""
    path = Path(path)
    if not path.exists():
        return []
    lines = path.read_bytes().split(b"\n")
    records = []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            if not isinstance(record, dict):
                raise ValueError("not a JSON object")
        except ValueError as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
            if any(rest.strip() for rest in lines[i:]):
                raise FileFormatError(f"{path}: line {i} is not a JSON record ({e}); fix or delete that line") \
                    from None
            log.warning(f"{path}: dropped its torn last line {line[:60].decode(errors='replace')!r} (a write "
                        f"was interrupted)")
            break
        records.append(record)
    return records


def remove_temp_files(folder: str | os.PathLike) -> int:
    """Remove the temp files (``TMP_PREFIX*``) unfinished atomic writes left in ``folder`` and below; only call
    it where no other process writes (e.g. under a ``FolderLock``). Returns how many were removed."""
    folder = Path(folder)
    found = [p for p in folder.rglob(f"{TMP_PREFIX}*") if p.is_file()] if folder.is_dir() else []
    for p in found:
        p.unlink(missing_ok=True)
    return len(found)
