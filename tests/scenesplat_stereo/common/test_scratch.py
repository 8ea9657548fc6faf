"""``common.scratch``: each process's scratch folder is its own and goes at its exit, a multiprocessing worker's
too (it ends with ``os._exit``, past ``atexit``), and a pool worker's ended by Ctrl-C; a killed process's folder is
removed by the next process that makes one, a living process's never; a slot's arrays read back in another
process."""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from scenesplat_stereo.common import scratch
from scenesplat_stereo.common.commandline import quiet_worker_interrupts
from tests.support.paths import REPO


def _child_folder(queue) -> None:
    queue.put(scratch.scratch_dir())


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_a_worker_process_removes_its_own_scratch_folder_and_not_its_parents(method):
    mine = scratch.scratch_dir()
    context = multiprocessing.get_context(method)
    queue = context.Queue()
    child = context.Process(target=_child_folder, args=(queue,))
    child.start()
    theirs = queue.get(timeout=60)
    child.join(60)
    assert child.exitcode == 0
    assert theirs != mine and not os.path.exists(theirs)  # the child's, gone with it
    assert os.path.isdir(mine)  # the parent's, untouched by the child's exit


def _folder_and_pid() -> tuple[str, int]:
    return scratch.scratch_dir(), os.getpid()


def test_a_pool_worker_ended_by_ctrl_c_removes_its_scratch_folder():
    """Ctrl-C ends a pool's worker with os._exit (``quiet_worker_interrupts``), past every exit handler."""
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=quiet_worker_interrupts)
    try:
        folder, pid = pool.submit(_folder_and_pid).result(timeout=60)
        assert os.path.isdir(folder)
        os.kill(pid, signal.SIGINT)
        deadline = time.monotonic() + 30
        while os.path.exists(folder):
            assert time.monotonic() < deadline, f"{folder} is still there"
            time.sleep(0.01)
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def test_a_process_removes_its_scratch_folder_at_exit():
    code = "from scenesplat_stereo.common import scratch; print(scratch.scratch_dir())"
    folder = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO)}).stdout.strip()
    assert folder and not os.path.exists(folder)


_HOLD = ("import sys, time; from scenesplat_stereo.common import scratch; s = scratch.Slot(); "
         "s.put({'a': __import__('numpy').ones(1000)}); print(scratch.scratch_dir(), flush=True); time.sleep(60)")


def _holder() -> tuple[subprocess.Popen, str]:
    """A process that made its scratch folder (and a slot file in it) and lives on; its folder."""
    proc = subprocess.Popen([sys.executable, "-c", _HOLD], stdout=subprocess.PIPE, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    return proc, proc.stdout.readline().strip()


def test_a_killed_processs_folder_goes_with_the_next_and_a_living_ones_stays():
    killed, dead_folder = _holder()
    living, live_folder = _holder()
    try:
        killed.kill()  # SIGKILL: no handler runs
        killed.wait(30)
        assert os.path.isdir(dead_folder) and len(os.listdir(dead_folder)) == 2  # the lock file and a slot
        code = "from scenesplat_stereo.common import scratch; print(scratch.scratch_dir())"
        subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, capture_output=True,
                       env={**os.environ, "PYTHONPATH": str(REPO)})
        assert not os.path.exists(dead_folder)  # removed by that process's first scratch_dir
        assert os.path.isdir(live_folder)  # its process holds the lock
        assert live_folder not in scratch.reap(os.path.dirname(live_folder))
    finally:
        living.kill()
        living.wait(30)
    assert live_folder in scratch.reap(os.path.dirname(live_folder))  # now its lock is free


def test_a_folder_without_an_owner_is_left_alone(tmp_path):
    """Its process may be starting, or of an earlier version and still running: only a free lock says it ended."""
    unowned, other = tmp_path / f"{scratch.PREFIX}unowned", tmp_path / "not-ours"
    for folder in (unowned, other):
        (folder / "slot").mkdir(parents=True)
    assert scratch.reap(str(tmp_path)) == []
    assert (unowned / "slot").is_dir() and (other / "slot").is_dir()


def test_a_folder_being_made_is_left_alone_by_another_processs_reap(monkeypatch):
    """Another process reaps while this one has made its folder and owner file but not locked it yet (two ranks
    of a distributed run start together): the folder stays, as its owner file is not there under its name until
    it is locked."""
    reaped, real_flock = [], scratch.fcntl.flock

    class Fcntl:  # the real fcntl, with another process's reap run just before this process's first lock
        LOCK_EX, LOCK_NB = scratch.fcntl.LOCK_EX, scratch.fcntl.LOCK_NB

        @staticmethod
        def flock(fd, op):
            if not reaped:
                base = os.path.dirname(os.path.dirname(os.readlink(f"/proc/self/fd/{fd}")))
                code = f"from scenesplat_stereo.common import scratch; print(scratch.reap({base!r}))"
                reaped.append(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                                             cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}).stdout)
            real_flock(fd, op)

    monkeypatch.setattr(scratch, "_scratch", {})  # this process makes a new folder
    monkeypatch.setattr(scratch, "fcntl", Fcntl)
    folder = scratch.scratch_dir()
    try:
        assert reaped and folder not in reaped[0]
        assert os.path.isdir(folder) and os.path.exists(os.path.join(folder, scratch.OWNER))
    finally:
        os.close(scratch._scratch["owner"])
        shutil.rmtree(folder, ignore_errors=True)


def _sum_in_worker(path: str, layout: scratch.Layout) -> dict[str, float]:
    return {name: float(a.astype(np.float64).sum()) for name, a in scratch.arrays_in(path, layout).items()}


def test_a_slot_carries_arrays_to_a_worker_and_grows():
    rng = np.random.default_rng(0)
    slot = scratch.Slot()
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        try:
            for n in (10, 100_000, 7):  # grows, then a smaller set in the larger file
                arrays = {"a": rng.random((n, 3), np.float32), "b": rng.integers(0, 255, (n,), np.uint8)}
                path, layout = slot.put(arrays)
                assert all(offset % scratch.ALIGN == 0 for _, offset, _, _ in layout)
                got = pool.submit(_sum_in_worker, path, layout).result(timeout=60)
                assert got == {k: float(v.astype(np.float64).sum()) for k, v in arrays.items()}
        finally:
            slot.close()
    assert not slot.path
