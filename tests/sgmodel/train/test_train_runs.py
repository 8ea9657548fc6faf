"""A resumed, interrupted, killed or refused ``sgmodel train`` never loses or poisons a checkpoint: real
processes stopped with SIGINT and SIGKILL, a second process on the same run folder, a torn metrics line, a
stale lock and temp file; and a diverged run stops before any checkpoint holds NaN, with advice that works
as written (docs/bad_input.md)."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from scenesplat_stereo.common.files import read_json_lines
from scenesplat_stereo.common.ownership import LOCK_FILE
from sgmodel.cli import main
from sgmodel.train import loop as train_mod
from tests.support.bad_input import refusal

STEPS = 30
TINY = ["--preset", "cpu-small", "--resolution", "32", "--padding", "2", "--val-every", "2", "--val-samples", "1",
        "--device", "cpu", "--no-progress"]


def command(data: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "sgmodel.cli", "train", "--data", str(data), "--out", str(out), *TINY,
            "--steps", str(STEPS), "--log-every", "1"]


def as_from_a_shell() -> None:
    """``preexec_fn`` of the runs this file signals: SIGINT at its default disposition and not blocked, as a
    shell starts a command, whatever this test process's own signal state (which a child inherits)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def wait_for(condition, what: str, timeout: float = 600) -> None:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def saved_step(run: Path) -> int:
    """The step last.pt holds, -1 while there is none (a replaced file is read whole or not at all)."""
    try:
        return torch.load(run / "checkpoints" / "last.pt", weights_only=True)["step"]
    except (FileNotFoundError, RuntimeError, EOFError):
        return -1


def assert_whole_and_finite(run: Path) -> int:
    ckpt = torch.load(run / "checkpoints" / "last.pt", weights_only=True)
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())
    return ckpt["step"]


def test_interrupted_killed_and_refused_runs_keep_their_checkpoint(demo_dataset, tmp_path):
    # 1. Ctrl-C (SIGINT to the process group, as a terminal sends it: the run and its loader workers) after the
    # first checkpoint: exit 130, one line, last.pt whole, the lock released. A run that finished before the
    # signal reached it (a loaded machine can hold up this process's polling for the seconds the run has left)
    # is started again in a fresh folder, at most three times.
    for attempt in range(3):
        run = tmp_path / f"run{attempt}"
        cmd = command(demo_dataset, run)
        first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 preexec_fn=as_from_a_shell, start_new_session=True)
        wait_for(lambda: saved_step(run) >= 2, "the first checkpoint")
        os.killpg(first.pid, signal.SIGINT)
        out, err = first.communicate(timeout=300)
        if not (first.returncode == 0 and saved_step(run) == STEPS):
            break
    assert first.returncode == 130, f"attempt {attempt}, last.pt at step {saved_step(run)}: {err} {out[-600:]}"
    step = assert_whole_and_finite(run)
    assert "sgmodel train: interrupted: at step" in err and "Traceback" not in err, err
    assert f"last.pt holds step {step}: rerun the same command to resume" in err, err
    assert not (run / LOCK_FILE).exists()

    # 2. resume; a second process on the same run folder is refused while it runs (stopped with SIGSTOP, so
    # that it cannot finish meanwhile); then SIGKILL after its next checkpoint
    second = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              preexec_fn=as_from_a_shell)
    wait_for(lambda: (run / LOCK_FILE).exists() and (run / LOCK_FILE).read_text().strip() == str(second.pid),
             "the resumed run's lock")
    second.send_signal(signal.SIGSTOP)
    before = (run / "checkpoints" / "last.pt").read_bytes()
    refused = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert refused.returncode == 2 and f"another `sgmodel train` (pid {second.pid}) is writing it" in refused.stderr
    assert (run / "checkpoints" / "last.pt").read_bytes() == before
    second.send_signal(signal.SIGCONT)
    wait_for(lambda: saved_step(run) > step, "a checkpoint of the resumed run")
    second.kill()  # SIGKILL: no cleanup at all
    second.communicate(timeout=60)
    step = assert_whole_and_finite(run)
    assert (run / LOCK_FILE).read_text().strip() == str(second.pid)  # left behind by the dead process

    # what a kill can leave: a torn last metrics line, a half-written checkpoint temp file
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"step": 99, "lo')
    (run / "checkpoints" / ".tmp-last.pt.x1y2z3").write_bytes(b"half a checkpoint")

    # 3. resume to the end: the stale lock is taken over, the torn line dropped, the temp file swept
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert f"resuming at step {step}" in done.stdout
    assert f"took over the lock of pid {second.pid}" in done.stderr
    assert "metrics.jsonl: dropped its torn last line" in done.stderr
    assert assert_whole_and_finite(run) == STEPS and not list(run.rglob(".tmp-*")) and not (run / LOCK_FILE).exists()
    logged = [r["step"] for r in read_json_lines(run / "metrics.jsonl") if "loss" in r]
    assert logged == list(range(1, STEPS + 1))  # every step logged once: nothing lost, nothing twice

    # 4. the same weights as a run that was never stopped
    whole = tmp_path / "whole"
    assert subprocess.run(command(demo_dataset, whole), capture_output=True, timeout=600).returncode == 0
    a = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["model"]
    b = torch.load(whole / "checkpoints" / "last.pt", weights_only=True)["model"]
    for k in a:
        assert torch.equal(a[k], b[k]), k


class _NanGradient(torch.autograd.Function):
    """Passes the loss through unchanged and sends NaN back: a finite loss with non-finite gradients."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, g):
        return g * float("nan")


def diverging(monkeypatch, at_call: int, how: str) -> None:
    """Make the objective's ``at_call``-th call give a NaN loss (``how="loss"``) or NaN gradients ("grad")."""
    real = train_mod.create_objective

    def create(*args, **kwargs):
        objective, calls = real(*args, **kwargs), {"n": 0}
        inner = objective.__call__

        class Diverging(type(objective)):
            def __call__(self, render, target):
                loss, parts = inner(render, target)
                if render.requires_grad:
                    calls["n"] += 1
                    if calls["n"] >= at_call:
                        loss = loss * float("nan") if how == "loss" else _NanGradient.apply(loss)
                return loss, parts

        objective.__class__ = Diverging
        return objective

    monkeypatch.setattr(train_mod, "create_objective", create)


def fused_optimiser(monkeypatch) -> None:
    """The run's AdamW fused, as on CUDA (fused runs on the CPU too): a non-finite loss then skips its update on
    the device, and the loop learns of it when it reads the step's values, after the next step is queued."""
    real = train_mod.create_optimizer
    monkeypatch.setattr(train_mod, "create_optimizer", lambda params, device, **kw: torch.optim.AdamW(
        params, fused=True, **kw) if device.type == "cpu" else real(params, device, **kw))


@pytest.mark.parametrize("how,at_call,what,fused", [("loss", 3, "the loss is nan", False),
                                                    ("loss", 3, "the loss is nan", True),
                                                    ("grad", 3, "a gradient is NaN or infinite", False)])
def test_a_diverged_run_keeps_its_last_finite_checkpoint_and_the_advice_works(demo_dataset, tmp_path, capsys,
                                                                             monkeypatch, how, at_call, what, fused):
    run = tmp_path / "run"
    argv = ["train", "--data", demo_dataset, "--out", run, *TINY, "--steps", "6", "--log-every", "2"]
    diverging(monkeypatch, at_call, how)
    if fused:  # step 3's values are read while step 4 is queued: the error still names step 3
        fused_optimiser(monkeypatch)
    rc, err = refusal(main, argv, capsys)
    step = 3 if how == "loss" else 4  # a NaN gradient is read at the next log step, before the checkpoint there
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert f"training diverged at step {step}: {what}; nothing of it was saved ({run}/checkpoints/last.pt holds " \
           f"step 2)" in err, err
    assert assert_whole_and_finite(run) == 2
    best = torch.load(run / "checkpoints" / "best.pt", weights_only=True)
    assert best["step"] == 2 and all(torch.isfinite(v).all() for v in best["model"].values())
    advice = shlex.split(err.split("; the command: ", 1)[1])
    assert advice[:2] == ["sgmodel", "train"] and "--init-from" in advice and "--lr" in advice
    monkeypatch.undo()
    rc, err = refusal(main, advice[1:], capsys)  # the advice, as written
    assert rc == 0, err
    new = Path(advice[advice.index("--out") + 1])
    config = json.loads((new / "config.json").read_text())
    assert new != run and config["init_from"]["step"] == 2 and config["train"]["lr"] == pytest.approx(4e-4 / 2)
    assert assert_whole_and_finite(new) == 6


def test_a_run_that_diverges_before_its_first_checkpoint_reruns_in_place(demo_dataset, tmp_path, capsys,
                                                                         monkeypatch):
    run = tmp_path / "run"
    diverging(monkeypatch, 1, "loss")
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", run, *TINY, "--steps", "2"], capsys)
    assert rc == 2 and "training diverged at step 1: the loss is nan" in err
    assert "no checkpoint was written before it" in err and not (run / "checkpoints").exists()
    advice = shlex.split(err.split("; the command: ", 1)[1])
    assert Path(advice[advice.index("--out") + 1]) == run and "--init-from" not in advice
    monkeypatch.undo()
    rc, err = refusal(main, advice[1:], capsys)
    assert rc == 0 and "an earlier attempt with other settings saved no checkpoint; starting afresh" in err, err
    assert assert_whole_and_finite(run) == 2


def test_the_finiteness_check_is_one_fused_reduction():
    tensors = [torch.randn(5, 3), torch.randn(7)]
    assert train_mod.all_finite(tensors).item() and train_mod.all_finite([]).item()
    for bad in (float("nan"), float("inf"), -float("inf")):
        broken = [t.clone() for t in tensors]
        broken[1][4] = bad
        assert not train_mod.all_finite(broken).item()


def test_a_run_killed_before_its_first_checkpoint_starts_again(demo_dataset, tmp_path):
    run = tmp_path / "run"
    cmd = command(demo_dataset, run)[:-4] + ["--steps", "2"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_for(lambda: (run / "config.json").exists(), "the run's config.json")
    p.kill()
    p.communicate(timeout=60)
    assert saved_step(run) == -1  # killed before any checkpoint
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and "sgmodel train: new run" in done.stdout, done.stderr
    assert assert_whole_and_finite(run) == 2
