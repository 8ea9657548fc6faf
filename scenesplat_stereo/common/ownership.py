"""Ownership, the one owner of "may this command replace what is there", and one writer per folder.

* ``check_replaceable``: every output folder gets a manifest (``OWNER_FILE``: the command, and every file it
  wrote with its size and sha256), and a command replaces a folder only when every file in it is one it wrote,
  unchanged; otherwise it refuses, naming a file that is not. ``StagedFolder``: a report or prediction folder
  is built beside its target and swapped in whole, so an earlier one never leaves stale files beside the new
  ones; staging folders of dead processes are swept on the next run. ``OwnedFolder``: a folder written in
  place. A symbolic link the command made (COLMAP's staged images) is recorded as a link to its target.
* A single-file output (``inspect --contact-sheet``, the benches' ``--out``, ``pack --out``,
  ``irs-pose-recovery recover --out``) has a manifest of its own beside it (``.written-by.<name>``):
  ``check_replaceable_file`` before any work, ``write_owned_file`` to write it; ``OwnedFile`` holds the two
  for a command (checked when made, written once the work is done).
* ``FolderLock``: one process at a time writes a folder (``fcntl.flock`` on ``<folder>/.lock``, which
  holds the pid); the kernel drops the lock when its process dies, so a stale lock file is taken over.
* ``check_writable`` / ``check_apart``: an output folder can be written (creating nothing) and is apart from
  the inputs, before anything is written.

Every check raises a ``ValueError`` naming the flag and the path. The writes themselves: ``common.files``.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from scenesplat_stereo.common.files import TMP_PREFIX, atomic_write_bytes, atomic_write_json

OWNER_FILE = ".written-by"  # the manifest of an output folder: the command that wrote it and every file it wrote
HASH_LIMIT = 64 << 20  # files up to this size are remembered by their sha256, larger ones by their mtime
LOCK_FILE = ".lock"  # FolderLock's file: the pid of the process that holds the lock
log = logging.getLogger(__name__)


class FolderBusy(ValueError):
    """Another live process holds a ``FolderLock`` on the folder."""


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


def file_record(path: Path) -> dict:
    """What an ownership manifest remembers of a file: its size, and its sha256 (up to ``HASH_LIMIT`` bytes)
    or, for a larger one, its modification time in nanoseconds (hashing gigabytes on every run costs too much);
    of a symbolic link, where it points (a link put in place of a file, or pointed elsewhere, is a change)."""
    if path.is_symlink():
        return {"link": os.readlink(path)}
    st = path.stat()
    if st.st_size > HASH_LIMIT:
        return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return {"size": st.st_size, "sha256": digest.hexdigest()}


def _contents(folder: Path) -> list[Path]:
    """The files under ``folder`` (any depth) that count: not the manifests (``OWNER_FILE``, and the
    ``OWNER_FILE.<name>`` of single files), the lock, or temp files of unfinished writes (``TMP_PREFIX``)."""
    def counts(p: Path) -> bool:
        manifest = p.name == OWNER_FILE or p.name.startswith(f"{OWNER_FILE}.")
        return not manifest and p.name != LOCK_FILE and not any(part.startswith(TMP_PREFIX) for part in
                                                                p.relative_to(folder).parts)

    return sorted(p for p in folder.rglob("*") if (p.is_file() or p.is_symlink()) and counts(p))


def write_manifest(folder: str | os.PathLike, owner: str, open_: bool = False) -> Path:
    """Record in ``folder/OWNER_FILE`` that ``owner`` (e.g. "sgmodel predict") wrote every file now under
    ``folder``, each with its ``file_record``: what ``check_replaceable`` later reads to decide whether the
    folder may be replaced. Call it when the command has written the folder (also when it stops early: what
    it wrote is then known to be its own). ``open_``: ``owner`` is writing the folder now; if it is killed
    before it closes the manifest, what it added is taken as its own by its rerun (which resumes)."""
    folder = Path(folder)
    files = {str(p.relative_to(folder)): file_record(p) for p in _contents(folder)}
    doc = {"owner": owner, "files": files} | ({"open": True} if open_ else {})
    return atomic_write_json(folder / OWNER_FILE, doc, indent=None, sort_keys=True)


def _manifest(path: Path) -> dict | None:
    """The manifest in the file ``path`` (a folder's ``OWNER_FILE``): {"owner", "files"}, {"owner": name} for a
    marker of an earlier version (the command's name alone, no file list), or None (none, or unreadable)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError):
        return None
    try:
        doc = json.loads(text)
    except ValueError:
        return {"owner": text.strip()} if text.strip() and "\n" not in text.strip() else None
    if not (isinstance(doc, dict) and isinstance(doc.get("owner"), str) and isinstance(doc.get("files"), dict)):
        return None
    return doc


def foreign_file(folder: str | os.PathLike, owner: str) -> str | None:
    """None when every file under ``folder`` is ``owner``'s (its manifest lists it, same size and hash), or
    when the folder is absent or empty; otherwise why not, naming one file: the one owner of "may this
    command replace what is there"."""
    folder = Path(folder)
    found = _contents(folder) if folder.is_dir() else []
    if not found:
        return None
    manifest = _manifest(folder / OWNER_FILE)
    first = str(found[0].relative_to(folder))
    if manifest is None:
        return f"holds files not written by `{owner}` (e.g. {first!r})"
    if manifest["owner"] != owner:
        return f"holds the output of `{manifest['owner']}`"
    if "files" not in manifest:
        return (f"holds the output of an earlier version of `{owner}`, which kept no list of its files (e.g. "
                f"{first!r}); delete it yourself if you no longer need it")
    if manifest.get("open"):  # a run of owner's that was killed: what it left is its own, and its rerun resumes
        return None
    for p in found:
        name = str(p.relative_to(folder))
        if name not in manifest["files"]:
            return f"holds files not written by `{owner}` (e.g. {name!r})"
        if file_record(p) != manifest["files"][name]:
            return f"holds {name!r}, changed since `{owner}` wrote it"
    return None


def check_replaceable(folder: str | os.PathLike, flag: str, owner: str, marker: str | None = None) -> Path:
    """``folder`` may be (re)written by ``owner`` (e.g. "sgmodel predict"): absent, empty, or every file in it
    ``owner``'s (``foreign_file``), and creatable or writable; ValueError naming ``flag`` and a file that is
    not ``owner``'s otherwise. ``marker``: for commands that resume (train, build, encode), a folder holding
    this file is theirs, and their own rules decide (settings, fingerprints). A symbolic link is followed:
    the folder it points to is the one checked and written. Creates nothing; returns the folder to write."""
    folder = Path(folder)
    if folder.is_symlink():
        folder = folder.resolve()
    check_writable(folder, flag, create=False)  # a folder, or creatable (names the file standing in the way)
    if folder.exists() and folder.parent != folder:
        check_writable(folder.parent, flag, create=False)  # replacing it renames it
    if marker is not None and (folder / marker).is_file():
        return folder
    why = foreign_file(folder, owner)
    if why is not None:
        raise ValueError(f"{flag} {folder}: {why}, and `{owner}` replaces only what it wrote; choose a new or empty "
                         f"{flag}")
    return folder


def _own_manifest(path: Path) -> Path:
    """Where the manifest of a single-file output lives: ``.written-by.<name>`` beside it."""
    return path.with_name(f"{OWNER_FILE}.{path.name}")


def check_replaceable_file(path: str | os.PathLike, flag: str, owner: str) -> Path:
    """The single-file output ``path`` may be (re)written by ``owner``: absent, or a file its own manifest
    (``_own_manifest``, the format of a folder's) records as ``owner``'s, unchanged (or being written by a run
    that was killed: open); and its folder writable or creatable. ValueError naming ``flag``, the file and why
    otherwise. A symbolic link is followed. Creates nothing; returns the file to write."""
    path = Path(path).resolve() if Path(path).is_symlink() else Path(path)
    if path.is_dir():
        raise ValueError(f"{flag} {path}: is a folder; give the name of the file to write")
    check_writable(path.parent, flag, create=False)
    if not path.exists():
        return path
    manifest = _manifest(_own_manifest(path))
    if manifest is None or "files" not in manifest:
        why = f"was not written by `{owner}` (no {_own_manifest(path).name} beside it)"
    elif manifest["owner"] != owner:
        why = f"is the output of `{manifest['owner']}`"
    elif manifest.get("open") or manifest["files"].get(path.name) == file_record(path):
        return path
    else:
        why = f"changed since `{owner}` wrote it"
    raise ValueError(f"{flag} {path}: exists and {why}, and `{owner}` replaces only what it wrote; choose another "
                     f"{flag}, or move the file away")


def write_owned_file(path: str | os.PathLike, data: bytes, owner: str) -> Path:
    """Write the single-file output ``path`` (checked with ``check_replaceable_file``) atomically, with its own
    manifest: marked open first, closed with the file's record once the file is in place (a run killed in
    between leaves it open, so its rerun may replace the file)."""
    path, manifest = Path(path), _own_manifest(Path(path))
    atomic_write_json(manifest, {"owner": owner, "files": {}, "open": True}, indent=None, sort_keys=True)
    atomic_write_bytes(path, data)
    atomic_write_json(manifest, {"owner": owner, "files": {path.name: file_record(path)}}, indent=None, sort_keys=True)
    return path


class OwnedFile:
    """A command's single-file output (a flag such as ``--out FILE``; None: none asked for), one object for its
    check and its write: made before any work (``check_replaceable_file``: a file the command may not replace is
    refused at once, naming ``flag``), written when the work is done (``write``: ``write_owned_file``)."""

    def __init__(self, path: str | os.PathLike | None, flag: str, owner: str) -> None:
        self.owner = owner
        self.path = None if path is None else check_replaceable_file(path, flag, owner)

    def write(self, data: bytes | str) -> Path | None:
        """Write ``data`` (text as UTF-8) to the file atomically with its manifest; the path, or None when none
        was asked for."""
        if self.path is None:
            return None
        return write_owned_file(self.path, data.encode() if isinstance(data, str) else data, self.owner)


class OwnedFolder:
    """``with OwnedFolder(folder, owner):`` for a command that writes files into ``folder`` in place (an
    importer's shards, rendered frames): on entry the manifest is marked open (the folder is being written);
    when the block ends, however it ends, ``write_manifest`` records every file there as ``owner``'s, so a
    rerun may replace them. Check with ``check_replaceable`` first."""

    def __init__(self, folder: str | os.PathLike, owner: str) -> None:
        self.folder, self.owner = Path(folder), owner

    def __enter__(self) -> Path:
        self.folder.mkdir(parents=True, exist_ok=True)
        write_manifest(self.folder, self.owner, open_=True)
        return self.folder

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.folder.is_dir():
            write_manifest(self.folder, self.owner)


class StagedFolder:
    """``with StagedFolder(target, owner) as tmp:`` write the new content into ``tmp`` (a hidden folder beside
    ``target``, same file system; a symbolic link ``target`` is followed); when the block ends normally, ``tmp``
    gets its manifest (``write_manifest``) and replaces ``target`` as a whole (two renames); when it raises,
    ``tmp`` is removed and ``target`` is untouched. On entry, staging folders of dead processes for the same
    target are swept, and an earlier ``target`` that such a process had moved aside (killed between the two
    renames) is put back. Check the target with ``check_replaceable`` before any work."""

    def __init__(self, target: str | os.PathLike, owner: str) -> None:
        target = Path(target)
        self.target, self.owner = (target.resolve() if target.is_symlink() else target.absolute()), owner
        self._prefix = f"{TMP_PREFIX}{self.target.name}.pid"
        self.tmp: Path | None = None

    def _sweep(self) -> None:
        for p in sorted(self.target.parent.glob(f"{self._prefix}*")):
            pid = p.name[len(self._prefix):].split(".", 1)[0]
            if not (p.is_dir() and pid.isdigit() and not pid_alive(int(pid))):
                continue
            if p.name.endswith(".old") and not self.target.exists():
                log.warning(f"{self.target}: put back the earlier folder that an interrupted run had moved aside")
                os.rename(p, self.target)
            else:
                shutil.rmtree(p, ignore_errors=True)

    def __enter__(self) -> Path:
        self.target.parent.mkdir(parents=True, exist_ok=True)
        self._sweep()
        self.tmp = Path(tempfile.mkdtemp(prefix=f"{self._prefix}{os.getpid()}.", dir=self.target.parent))
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                os.chmod(self.tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
                write_manifest(self.tmp, self.owner)
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


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


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
