"""Files and folders this project writes: every one appears whole or not at all.

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
* ``StagedFolder``: a report or prediction folder is built beside its target and swapped in whole, so an
  earlier one never leaves stale files beside the new ones; it replaces only a folder this project wrote
  (``OWNER_FILE``) or an empty one. Staging folders of dead processes are swept on the next run.
* ``FolderLock``: one process at a time writes a folder (``fcntl.flock`` on ``<folder>/.lock``, which
  holds the pid); the kernel drops the lock when its process dies, so a stale lock file is taken over.
* ``check_writable`` / ``check_apart``: an output folder can be written (creating nothing) and is apart from
  the inputs, before anything is written.

Every check raises a ``ValueError`` naming the flag and the path.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

TMP_PREFIX = ".tmp-"  # temp files and folders of unfinished writes start with this (a rerun may remove them)
OWNER_FILE = ".written-by"  # in a StagedFolder's result: the command that wrote it, e.g. "sgmodel predict"
LOCK_FILE = ".lock"  # FolderLock's file: the pid of the process that holds the lock
log = logging.getLogger(__name__)


class FileFormatError(ValueError):
    """A file that cannot be read as what it should be; the message names the file and the place."""


class FolderBusy(ValueError):
    """Another live process holds a ``FolderLock`` on the folder."""


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


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (a process of another user counts)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def check_writable(folder: str | os.PathLike, flag: str, create: bool = True) -> Path:
    """Prove ``folder`` writable with a temp file, before anything in it is written or removed; ValueError
    naming ``flag`` and the folder otherwise. ``create``: make the folder first; without it nothing is
    created: a missing folder's nearest existing ancestor must be a writable folder."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{flag} {folder}: exists and is not a folder")
    probe_in = folder
    if create:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"{flag} {folder}: cannot be created ({e.strerror or e})") from None
    else:
        while not probe_in.exists():
            probe_in = probe_in.parent
        if not probe_in.is_dir():
            raise ValueError(f"{flag} {folder}: cannot be created, {probe_in} is a file")
    try:
        fd, probe = tempfile.mkstemp(dir=probe_in, prefix=TMP_PREFIX)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        where = "" if probe_in == folder else f" (it would be created in {probe_in})"
        raise ValueError(f"{flag} {folder}: not writable{where} ({e.strerror or e})") from None
    return folder


def check_apart(out: str | os.PathLike, flag: str, inputs: dict[str, Any], replaced: bool = False) -> None:
    """ValueError naming both flags when the output ``out`` lies inside an input folder or file given as
    ``{flag: path, or a list of paths, or None}`` (a run folder inside the dataset), or, when ``out`` is
    ``replaced`` as a whole, when an input lies inside it (replacing it would delete the input)."""
    o = Path(out).resolve()
    for name, given in inputs.items():
        for path in given if isinstance(given, (list, tuple)) else [given]:
            if path is None:
                continue
            p = Path(path).resolve()
            if o == p or p in o.parents:
                raise ValueError(f"{flag} {out}: inside {name} {path}; write outputs apart from the inputs")
            if replaced and o in p.parents:
                raise ValueError(f"{flag} {out}: holds {name} {path}, and the whole folder is replaced; choose "
                                 f"another {flag}")


def _owner(folder: Path) -> str | None:
    try:
        return (folder / OWNER_FILE).read_text().strip()
    except OSError:
        return None


def check_replaceable(folder: str | os.PathLike, flag: str, owner: str) -> Path:
    """``folder`` may be replaced as a whole by ``owner`` (e.g. "sgmodel predict"): absent, empty, or written
    by ``owner`` (its ``OWNER_FILE`` says so), and creatable or writable; ValueError naming ``flag`` otherwise.
    Creates nothing."""
    folder = Path(folder)
    check_writable(folder.parent if folder.parent != folder else folder, flag, create=False)
    if folder.is_dir() and any(folder.iterdir()):
        found = _owner(folder)
        if found != owner:
            what = f"the output of `{found}`" if found else \
                f"files not written by `{owner}` (e.g. {sorted(p.name for p in folder.iterdir())[0]!r})"
            raise ValueError(f"{flag} {folder}: holds {what}, and `{owner}` replaces the whole folder; choose "
                             f"a new or empty {flag}")
    elif folder.exists() and not folder.is_dir():
        raise ValueError(f"{flag} {folder}: exists and is not a folder")
    return folder


class StagedFolder:
    """``with StagedFolder(target, owner) as tmp:`` write the new content into ``tmp`` (a hidden folder beside
    ``target``, same file system); when the block ends normally, ``tmp`` gets ``OWNER_FILE`` and replaces
    ``target`` as a whole (two renames: an interruption between them leaves ``target`` absent, never mixed);
    when it raises, ``tmp`` is removed and ``target`` is untouched. Staging folders of dead processes for
    the same target are swept on entry. Check the target with ``check_replaceable`` before any work."""

    def __init__(self, target: str | os.PathLike, owner: str) -> None:
        self.target, self.owner = Path(target).absolute(), owner
        self._prefix = f"{TMP_PREFIX}{self.target.name}.pid"
        self.tmp: Path | None = None

    def _sweep(self) -> None:
        for p in self.target.parent.glob(f"{self._prefix}*"):
            pid = p.name[len(self._prefix):].split(".", 1)[0]
            if p.is_dir() and pid.isdigit() and not pid_alive(int(pid)):
                shutil.rmtree(p, ignore_errors=True)

    def __enter__(self) -> Path:
        self.target.parent.mkdir(parents=True, exist_ok=True)
        self._sweep()
        self.tmp = Path(tempfile.mkdtemp(prefix=f"{self._prefix}{os.getpid()}.", dir=self.target.parent))
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                (self.tmp / OWNER_FILE).write_text(self.owner + "\n")
                old = None
                if self.target.exists():
                    old = self.tmp.with_name(self.tmp.name + ".old")
                    os.rename(self.target, old)
                os.rename(self.tmp, self.target)
                if old is not None:
                    shutil.rmtree(old, ignore_errors=True)
        finally:
            if self.tmp.exists():
                shutil.rmtree(self.tmp, ignore_errors=True)


class FolderLock:
    """An exclusive lock on ``folder`` (created if missing) for one process: ``acquire`` takes
    ``fcntl.flock`` on ``<folder>/.lock`` and writes this pid into it, or raises ``FolderBusy`` naming
    ``flag``, the folder and the pid holding it. A lock file left by a process that died is taken over (the
    kernel released its lock), with a warning. ``release`` removes the lock file, and the folders ``acquire``
    created that are still empty (a refused run leaves no trace). A context manager too."""

    def __init__(self, folder: str | os.PathLike, flag: str, owner: str) -> None:
        self.folder, self.flag, self.owner = Path(folder), flag, owner
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None
        self._created: list[Path] = []  # folders acquire made, deepest first

    def acquire(self) -> FolderLock:
        missing = self.folder.absolute()
        while not missing.exists():
            self._created.append(missing)
            missing = missing.parent
        self.folder.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                self._undo_folder()
                raise FolderBusy(f"{self.flag} {self.folder}: another `{self.owner}` (pid {holder}) is writing it; "
                                 f"wait until it ends, or choose another {self.flag}") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:  # not a file its last holder removed between our open and our lock
                break
            os.close(fd)
        stale = os.read(fd, 32).decode(errors="replace").strip()
        if stale:
            log.warning(f"{self.path}: took over the lock of pid {stale}, which ended without releasing it")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def _undo_folder(self) -> None:
        for folder in self._created:
            try:
                folder.rmdir()  # only while empty
            except OSError:
                break
        self._created = []

    def release(self) -> None:
        if self._fd is None:
            return
        self.path.unlink(missing_ok=True)
        os.close(self._fd)
        self._fd = None
        self._undo_folder()

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, exc_type, exc, tb) -> None:
        self.release()
