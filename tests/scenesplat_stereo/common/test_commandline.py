"""The one way out of every command (``scenesplat_stereo.common.commandline``): exit 2 with one line for what the user
can fix, 130 for Ctrl-C, 1 for a bug (traceback only on request), argparse's refusals in one line, warnings
named by the command; and the file helpers that keep outputs whole (``scenesplat_stereo.common.files``)."""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from scenesplat_stereo.common.commandline import (DEBUG_ENV, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_USAGE, Interrupted,
                                                  NotAvailable, Parser, one_line, run_command)
from scenesplat_stereo.common.files import FileFormatError, append_line, read_json, read_json_lines
from scenesplat_stereo.common.ownership import (LOCK_FILE, OWNER_FILE, FolderBusy, FolderLock, StagedFolder,
                                                check_replaceable)
from scenesplat_stereo.shards.webdataset import ShardError, ShardWriter, iter_shard
from tests.support.paths import REPO


def tool(raise_this: BaseException | None = None, warn: str | None = None) -> Parser:
    """A two-level command line ``tool do`` whose command raises ``raise_this`` (or logs ``warn``)."""
    parser = Parser(prog="tool")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("do")
    p.add_argument("--n", type=int, default=1)

    def run(args) -> int:
        if warn:
            logging.getLogger("some.module").warning(warn)
        if raise_this is not None:
            raise raise_this
        return 0

    p.set_defaults(func=run)
    return parser


def outcome(capsys, parser: Parser, argv: list[str]) -> tuple[int, str]:
    try:
        rc = run_command(parser, argv)
    except SystemExit as e:
        rc = e.code
    cap = capsys.readouterr()
    return rc, cap.err


OS_CASES = [
    (OSError(errno.ENOSPC, "No space left on device", "/runs/a/last.pt"),
     "tool do: error: /runs/a/last.pt: No space left on device (the disk is full: free space and rerun"),
    (PermissionError(errno.EACCES, "Permission denied", "/ro/out"),
     "tool do: error: /ro/out: Permission denied (permission denied: choose a folder you can write"),
    (NotADirectoryError(errno.ENOTDIR, "Not a directory", "/data/file/x"),
     "tool do: error: /data/file/x: Not a directory (a file stands where a folder is expected)"),
    (OSError(errno.EROFS, "Read-only file system", "/mnt/ro/x"),
     "tool do: error: /mnt/ro/x: Read-only file system (the file system is read-only: choose another folder)"),
    (OSError(errno.EEXIST, "File exists", "/a", None, "/b"), "tool do: error: /a -> /b: File exists"),
]


@pytest.mark.parametrize("exc,message", OS_CASES, ids=[type(c[0]).__name__ + str(c[0].errno) for c in OS_CASES])
def test_os_errors_name_the_file_and_what_to_do(capsys, exc, message):
    rc, err = outcome(capsys, tool(exc), ["do"])
    assert rc == EXIT_USAGE and err.startswith(message) and len(err.splitlines()) == 1, err


@pytest.mark.parametrize("exc,code,message", [
    (ValueError("--x 3: must be < 2"), EXIT_USAGE, "tool do: error: --x 3: must be < 2"),
    (NotAvailable("needs pycolmap: pip install pycolmap"), EXIT_USAGE, "tool do: error: needs pycolmap"),
    (tarfile.ReadError("unexpected end of data"), EXIT_USAGE, "tool do: error: corrupt tar archive: unexpected end"),
    (KeyboardInterrupt(), EXIT_INTERRUPTED, "tool do: interrupted"),
    (Interrupted("at step 7; last.pt holds step 6"), EXIT_INTERRUPTED, "tool do: interrupted: at step 7; last.pt"),
    (ZeroDivisionError("division by zero"), EXIT_INTERNAL,
     "tool do: error: internal error: ZeroDivisionError: division by zero (rerun with --debug"),
])
def test_each_class_has_its_exit_status_and_one_line(capsys, exc, code, message):
    rc, err = outcome(capsys, tool(exc), ["do"])
    assert rc == code and err.startswith(message) and len(err.splitlines()) == 1, err
    assert "Traceback" not in err


def test_debug_flag_and_environment_show_the_traceback(capsys, monkeypatch):
    rc, err = outcome(capsys, tool(ZeroDivisionError("x")), ["do", "--debug"])
    assert rc == EXIT_INTERNAL and "Traceback (most recent call last)" in err and err.rstrip().endswith(
        "please report it)")
    monkeypatch.setenv(DEBUG_ENV, "1")
    rc, err = outcome(capsys, tool(ValueError("bad")), ["do"])
    assert rc == EXIT_USAGE and "Traceback" in err and "tool do: error: bad" in err
    monkeypatch.setenv(DEBUG_ENV, "0")
    rc, err = outcome(capsys, tool(ValueError("bad")), ["do"])
    assert "Traceback" not in err


def test_argparse_refusals_are_one_line_naming_the_flag(capsys):
    rc, err = outcome(capsys, tool(), ["do", "--n", "x"])
    assert rc == EXIT_USAGE and err == "tool do: error: argument --n: invalid int value: 'x' (see `tool do --help`)\n"
    rc, err = outcome(capsys, tool(), ["do", "--nn", "1"])
    assert rc == EXIT_USAGE and "unrecognized arguments: --nn 1" in err and len(err.splitlines()) == 1


def test_warnings_are_named_by_the_command(capsys):
    rc, err = outcome(capsys, tool(warn="cx is far from the centre"), ["do"])
    assert rc == 0 and err == "tool do: warning: cx is far from the centre\n"


def test_user_errors_of_a_command_line_get_its_advice(capsys):
    rc = run_command(tool(MemoryError("CUDA out of memory. Tried to allocate 2 GiB")), ["do"],
                     {MemoryError: "out of memory: lower --batch-size"})
    err = capsys.readouterr().err
    assert rc == EXIT_USAGE and err.startswith("tool do: error: out of memory: lower --batch-size (CUDA out of")


def test_a_worker_traceback_becomes_its_last_line():
    text = ("Caught DataError in DataLoader worker process 0.\nOriginal Traceback (most recent call last):\n"
            '  File "x.py", line 3, in f\n    raise DataError(m)\nsgmodel.data.DataError: shard-000001.tar: '
            "member 'a.json': truncated")
    assert one_line(text) == "shard-000001.tar: member 'a.json': truncated"
    assert one_line("first\n  second") == "first second"


def test_both_command_lines_and_the_irs_tools_share_the_path():
    for module in ("scenesplat_stereo.cli", "sgmodel.cli", "pipelines.irs_targets", "pipelines.irs_pose_recovery"):
        done = subprocess.run([sys.executable, "-m", module, "--no-such-flag"], capture_output=True, text=True,
                              timeout=300)
        ours = [line for line in done.stderr.splitlines() if not line.startswith("Warp ")]  # Warp's CPU-only notice
        assert done.returncode == EXIT_USAGE and len(ours) == 1, (module, done.stderr)
        assert "error: unrecognized arguments: --no-such-flag" in done.stderr or "required" in done.stderr, module


# ---------------------------------------------------------------------------------------------- files


def test_read_json_names_the_file_line_and_column(tmp_path):
    path = tmp_path / "config.json"
    path.write_text('{"a": 1,\n "b": }')
    with pytest.raises(FileFormatError, match=r"config.json: not valid JSON \(line 2, column 7"):
        read_json(path)
    path.write_bytes(b'{"a": "\xff"}')
    with pytest.raises(FileFormatError, match="config.json: not UTF-8"):
        read_json(path)


def test_append_line_cuts_a_failed_write_back_off(tmp_path, monkeypatch):
    path = tmp_path / "metrics.jsonl"
    append_line(path, json.dumps({"step": 1}))
    real = os.write
    monkeypatch.setattr(os, "write", lambda fd, data: real(fd, data[:5]))  # a full disk: a short write
    with pytest.raises(OSError, match="No space left"):
        append_line(path, json.dumps({"step": 2, "loss": 0.5}))
    monkeypatch.setattr(os, "write", real)
    assert path.read_text() == '{"step": 1}\n'


def test_a_torn_last_line_is_dropped_with_a_warning_naming_the_file(tmp_path, caplog):
    path = tmp_path / "metrics.jsonl"
    path.write_text('{"step": 1}\n{"step": 2}\n{"step": 3, "lo')
    with caplog.at_level(logging.WARNING):
        assert read_json_lines(path) == [{"step": 1}, {"step": 2}]
    assert "metrics.jsonl: dropped its torn last line" in caplog.text
    path.write_text('{"step": 1}\nnot json\n{"step": 3}\n')
    with pytest.raises(FileFormatError, match="metrics.jsonl: line 2 is not a JSON record"):
        read_json_lines(path)


def test_a_truncated_shard_member_is_named(tmp_path):
    with ShardWriter(tmp_path, "train", 4) as w:
        w.add("a__000000", {"txt": b"first", "left.jpg": b"x" * 3000})
        w.add("a__000001", {"txt": b"second", "left.jpg": b"y" * 3000})
    shard = tmp_path / "train" / "shard-000000.tar"
    data = shard.read_bytes()
    shard.write_bytes(data[:len(data) // 2 + 700])  # cut inside the second sample's image
    with pytest.raises(ShardError, match=r"shard-000000.tar: member 'a__000001.left.jpg': truncated or corrupt tar"):
        list(iter_shard(shard))
    shard.write_bytes(b"not a tar at all" * 40)
    with pytest.raises(ShardError, match="shard-000000.tar: its first member: truncated or corrupt tar"):
        list(iter_shard(shard))


def test_staged_folder_replaces_the_whole_target_or_nothing(tmp_path):
    out = tmp_path / "out"
    with StagedFolder(out, "tool do") as tmp:
        (tmp / "scene.ply").write_text("first")
        (tmp / "depth.png").write_text("first")
    assert json.loads((out / OWNER_FILE).read_text()) == {"owner": "tool do", "files": {
        name: {"size": 5, "sha256": hashlib.sha256(b"first").hexdigest()} for name in ("depth.png", "scene.ply")}}
    with pytest.raises(RuntimeError):
        with StagedFolder(out, "tool do") as tmp:
            (tmp / "depth.png").write_text("second")
            raise RuntimeError("killed half-way")
    assert (out / "scene.ply").read_text() == "first"  # untouched by the failed attempt
    with StagedFolder(out, "tool do") as tmp:
        (tmp / "depth.png").write_text("third")
    assert sorted(p.name for p in out.iterdir()) == [OWNER_FILE, "depth.png"]  # no stale scene.ply
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no staging folder left behind


def test_staging_folders_of_dead_processes_are_swept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".tmp-out.pid{int(dead.stdout)}.abc123"
    stale.mkdir()
    (stale / "half.ply").write_text("x")
    alive = tmp_path / f".tmp-out.pid{os.getpid()}.def456"  # a live process's (ours): kept
    alive.mkdir()
    with StagedFolder(tmp_path / "out", "tool do"):
        pass
    assert not stale.exists() and alive.exists()


def test_check_replaceable_refuses_a_folder_of_other_files(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("years of work")
    with pytest.raises(ValueError, match=r"--out .*mine: holds files not written by `tool do` \(e.g. 'thesis.tex'\)"):
        check_replaceable(tmp_path / "mine", "--out", "tool do")
    with StagedFolder(tmp_path / "other", "other tool") as tmp:
        (tmp / "report.md").write_text("theirs")
    with pytest.raises(ValueError, match="holds the output of `other tool`"):
        check_replaceable(tmp_path / "other", "--out", "tool do")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="exists and is not a folder"):
        check_replaceable(tmp_path / "file", "--out", "tool do")
    check_replaceable(tmp_path / "new" / "deeper", "--out", "tool do")
    assert not (tmp_path / "new").exists()  # checks create nothing


def test_folder_lock_refuses_a_second_holder_and_takes_over_a_dead_ones(tmp_path, caplog):
    run = tmp_path / "run"
    with FolderLock(run, "--out", "tool do"):
        assert (run / LOCK_FILE).read_text() == f"{os.getpid()}\n"
        with pytest.raises(FolderBusy, match=rf"--out .*run: another `tool do` \(pid {os.getpid()}\) is writing it"):
            FolderLock(run, "--out", "tool do").acquire()
    assert not run.exists()  # the lock made the folder, and nothing else was written: both gone
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    run.mkdir()
    (run / LOCK_FILE).write_text(dead.stdout)  # left by a process that was killed
    with caplog.at_level(logging.WARNING), FolderLock(run, "--out", "tool do"):
        assert (run / LOCK_FILE).read_text() == f"{os.getpid()}\n"
    assert f"took over the lock of pid {int(dead.stdout)}" in caplog.text
    assert run.is_dir() and not (run / LOCK_FILE).exists()


def test_the_irs_tools_run_as_scripts_from_anywhere_and_as_installed_commands(tmp_path):
    """``python pipelines/<tool>.py`` from another folder, and the console commands of pyproject.toml."""
    root = REPO
    for tool in ("irs_pose_recovery", "irs_targets"):
        done = subprocess.run([sys.executable, str(root / "pipelines" / f"{tool}.py"), "--help"], capture_output=True,
                              text=True, cwd=tmp_path, timeout=300)
        assert done.returncode == 0 and f"usage: {tool.replace('_', '-')}" in done.stdout, done.stderr[-1000:]
    for command in ("irs-pose-recovery", "irs-targets"):
        script = Path(sys.executable).parent / command
        assert script.is_file(), f"{command} is not installed: pip install -e ."
        done = subprocess.run([str(script), "--help"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
        assert done.returncode == 0 and f"usage: {command}" in done.stdout, done.stderr[-1000:]
