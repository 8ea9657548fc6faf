"""Scratch space in RAM: this process's private scratch folder, and the slots that carry arrays to worker processes.

* ``scratch_dir``: a private folder in ``/dev/shm`` when it has ``SHM_MIN_FREE`` free (containers often give it
  64 MB), else in the system's temporary folder; created on first use in each process, removed at its exit
  (a multiprocessing worker's too, though it ends past ``atexit``, and a worker's ended by Ctrl-C). A process that
  ends past every handler (killed, or a crash) leaves its folder, slot files and all: the next process to make
  one removes it (``reap``). Each folder holds ``OWNER``, locked (``flock``) by its process while it lives: the
  kernel drops the lock with the process however it ends, and in any PID namespace sharing the folder.
* ``Slot``: a file in that folder mapped in the calling process (grown as needed) and, by path, in a worker
  process (``arrays_in``). The caller copies named arrays in (one ``memcpy`` each, without the GIL) and sends only
  the path and the layout through the pool's pipe; the worker reads them in place. Pickled through the pipe
  instead, a big array queues for the GIL between the pipe's 64 KiB chunks. The calling thread owns a slot from
  ``put`` until the worker's result is back. Users: the shard build's encoder processes
  (``shards.encode_pool``) and the writers of ``sgmodel predict --video --frames`` (``sgmodel.predict.scene_writers``).
"""

from __future__ import annotations

import fcntl
import itertools
import mmap
import multiprocessing.util
import os
import shutil
import tempfile
import threading

import numpy as np

#: ``/dev/shm`` holds the scratch folder only with this much room, else the system temp folder.
SHM_MIN_FREE = 1 << 30
#: Bytes; each array in a slot starts on a cache line.
ALIGN = 64
#: Scratch folders' name prefix, and the file in each that its process keeps locked while it lives.
PREFIX, OWNER = "scenesplat-scratch-", ".owner"

# (name, offset in bytes, shape, dtype string) of each array in a slot
Layout = list[tuple[str, int, tuple[int, ...], str]]

_scratch_lock = threading.Lock()
_scratch: dict[str, object] = {}  # {"pid": ..., "dir": ..., "owner": the locked file's descriptor} of this process
_slot_ids = itertools.count()
_maps: dict[str, mmap.mmap] = {}  # in a worker: slot path -> its mapping


def scratch_dir() -> str:
    """This process's private scratch folder (created on first use, removed at exit)."""
    pid = str(os.getpid())
    with _scratch_lock:
        if _scratch.get("pid") != pid:
            if "owner" in _scratch:  # a forked child's copy of its parent's: the parent's lock is the parent's
                os.close(_scratch.pop("owner"))
            base = "/dev/shm" if free_bytes("/dev/shm") >= SHM_MIN_FREE else None
            path = tempfile.mkdtemp(prefix=PREFIX, dir=base)
            # locked under another name, then renamed: ``reap`` never finds an OWNER that is not locked yet
            unnamed = os.path.join(path, OWNER + ".new")
            owner = os.open(unnamed, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
            fcntl.flock(owner, fcntl.LOCK_EX)  # a new file: no one else holds it
            os.rename(unnamed, os.path.join(path, OWNER))
            _scratch.update(pid=pid, dir=path, owner=owner)
            reap(os.path.dirname(path))
            # at exit: atexit's in any process, multiprocessing's too in a worker it started (which ends with
            # os._exit, past atexit); a forked child's copy of the parent's finaliser leaves the parent's folder
            multiprocessing.util.Finalize(None, remove_own, exitpriority=0)
        return _scratch["dir"]


def remove_own() -> None:
    """Remove this process's scratch folder now, if it made one: its exit finaliser, and a process about to end
    with ``os._exit`` (a worker on Ctrl-C, ``commandline.quiet_worker_interrupts``). Takes no lock, so a signal
    handler may call it."""
    mine = dict(_scratch)
    if mine.get("pid") == str(os.getpid()):
        shutil.rmtree(mine["dir"], ignore_errors=True)


def reap(base: str) -> list[str]:
    """Remove the scratch folders in ``base`` whose process has ended (their ``OWNER`` lock is free); returns their
    paths. A folder without ``OWNER`` (its process just starting, or of an earlier version, which may still run),
    another user's, and any that cannot be read or locked are left alone."""
    removed = []
    try:
        names = [n for n in os.listdir(base) if n.startswith(PREFIX)]
    except OSError:
        return removed
    for name in names:
        path = os.path.join(base, name)
        if path == _scratch.get("dir"):
            continue
        try:
            fd = os.open(os.path.join(path, OWNER), os.O_RDWR)
        except OSError:  # no owner file, another user's, or not a folder
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held while its process lives
        except OSError:
            os.close(fd)
            continue
        try:
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
        finally:
            os.close(fd)
    return removed


def free_bytes(path: str) -> int:
    """Bytes free to us in the file system of ``path`` (0 if it is missing or not writable)."""
    if not os.access(path, os.W_OK):
        return 0
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


class Slot:
    """A shared buffer for one set of arrays at a time: a file in ``folder`` (default ``scratch_dir()``) mapped here
    (grown as needed) and, by path, in the workers (``arrays_in``)."""

    def __init__(self, folder: str | None = None) -> None:
        self.folder, self.path, self.buf = folder or scratch_dir(), "", None

    def put(self, arrays: dict[str, np.ndarray]) -> tuple[str, Layout]:
        """Copy named ``arrays`` into the slot; returns (path, layout) for ``arrays_in``."""
        layout, offset = [], 0
        for name, a in arrays.items():
            layout.append((name, offset, tuple(a.shape), a.dtype.str))
            offset += -(-a.nbytes // ALIGN) * ALIGN
        if self.buf is None or len(self.buf) < offset:
            self._grow(offset)
        for (name, off, shape, dtype) in layout:
            np.copyto(np.ndarray(shape, dtype, buffer=self.buf, offset=off), arrays[name], casting="no")
        return self.path, layout

    def _grow(self, nbytes: int) -> None:
        self.close()  # a new file (a new name): workers map it afresh and drop the old one
        self.path = os.path.join(self.folder, f"slot-{os.getpid()}-{next(_slot_ids)}")
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.ftruncate(fd, max(nbytes, 1))
            self.buf = mmap.mmap(fd, max(nbytes, 1))
        finally:
            os.close(fd)

    def close(self) -> None:
        if self.buf is not None:
            self.buf.close()
            self.buf = None
        if self.path:
            try:
                os.remove(self.path)
            except FileNotFoundError:
                pass
            self.path = ""


def arrays_in(path: str, layout: Layout) -> dict[str, np.ndarray]:
    """In a worker: views of the arrays ``Slot.put`` copied to ``path``. No view may outlive the task (the
    mapping of a removed slot file is closed on a later miss)."""
    buf = _maps.get(path)
    if buf is None:
        for old in [p for p in _maps if not os.path.exists(p)]:
            _maps.pop(old).close()
        with open(path, "r+b") as f:
            buf = _maps[path] = mmap.mmap(f.fileno(), 0)
    return {name: np.ndarray(shape, dtype, buffer=buf, offset=off) for name, off, shape, dtype in layout}
