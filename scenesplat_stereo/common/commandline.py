"""What every command line of the project shares: parsing what users type, and the one way out of a command.

Used by ``scenesplat-stereo``, ``sgmodel`` and the IRS tools (``irs-pose-recovery``, ``irs-targets``).

``Parser`` is ``argparse.ArgumentParser`` with prefix matching off (``allow_abbrev=False``): a mistyped or
shortened flag is refused instead of silently landing on another (``--rig`` is not ``--right``). Sub-command
parsers made through ``add_subparsers`` inherit the class, so every level refuses abbreviations, accepts
``--debug`` and prints argparse's own refusals as one line.

A command line is a table (``Command``): each entry names a sub-command and the module that holds it, with
``add_arguments(parser)`` and ``run(args)``; ``add_commands`` builds the parsers from it.

``run_command(parser, argv)`` parses, calls ``args.func(args)`` and turns every way a command can end into
one exit status and at most one line on stderr, ``<command>: error: <what>``:

* 0: done.
* 2 (``EXIT_USAGE``): bad arguments or input, which the user fixes: argparse's refusals, every ``ValueError`` a
  command raises on purpose (each module raises its own subclass, or a ``ValueError`` in a ``raise`` statement,
  naming the flag, or the file and the field: JSON that does not parse, a truncated shard member, a checkpoint of
  another version, a CUDA device that is not there; a library's ``ValueError`` counts too, its message names what
  it could not read), ``NotAvailable`` (a package or library that is not installed), every ``OSError`` (named with
  its file and what to do: a read-only folder, a full disk, a file where a folder is expected), and the error
  classes a command adds (``user_errors``, e.g. running out of GPU memory).
* 130 (``EXIT_INTERRUPTED``): Ctrl-C (SIGINT); ``Interrupted`` carries what was kept (a rerun resumes). Worker
  processes of pools end silently (``quiet_worker_interrupts``, their initializer).
* 1 (``EXIT_INTERNAL``): anything else is a bug, a ``ValueError`` no one raised on purpose included (unpacking,
  ``int()`` or ``list.index`` failing in our own code: ``our_bug``): one line naming the exception; the traceback
  only with ``--debug`` or ``STEREOGAUSSIANS_DEBUG=1`` (either also prints it for the errors above).

Warnings go through ``logging`` (``log = logging.getLogger(__name__)``; ``log.warning(...)``): while a
command runs they print as ``<command>: warning: <what>`` on stderr.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import linecache
import logging
import os
import signal
import sys
import tarfile
import traceback
from collections.abc import Mapping
from dataclasses import dataclass

EXIT_OK, EXIT_INTERNAL, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
OUR_PACKAGES = ("scenesplat_stereo", "sgmodel", "pipelines")  # whose explicit ValueErrors are refusals of input
DEBUG_ENV = "STEREOGAUSSIANS_DEBUG"  # set to anything but "" or "0" for tracebacks
_COMMAND = "command_name"  # namespace attribute: the prog of the deepest (sub-)parser, e.g. "sgmodel train"

#: What to do about an OSError, by errno (the message names the file and says what happened first).
_OS_ADVICE = {
    errno.ENOSPC: "the disk is full: free space and rerun (finished files are kept)",
    errno.EDQUOT: "the disk quota is exceeded: free space and rerun",
    errno.EACCES: "permission denied: choose a folder you can write, or fix its permissions",
    errno.EPERM: "permission denied: choose a folder you can write, or fix its permissions",
    errno.EROFS: "the file system is read-only: choose another folder",
    errno.ENOTDIR: "a file stands where a folder is expected",
    errno.EISDIR: "a folder stands where a file is expected",
    errno.ENOENT: "no such file or folder",
    errno.ENAMETOOLONG: "the name is too long",
    errno.EIO: "input/output error: the disk or the network file system failed",
}


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, with a message saying what was kept and how to go on (e.g. rerun to resume)."""


class NotAvailable(RuntimeError):
    """Something a command needs is not on this machine (a package, a library, a GPU); the message says how
    to get it. The user fixes it: exit 2."""


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` that never takes an abbreviation of a long flag for the flag, takes ``--debug``
    at every level, records its ``prog`` as the command's name and refuses in one line."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        self.set_defaults(**{_COMMAND: self.prog})
        self.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                          help=f"print the traceback of an error (also: {DEBUG_ENV}=1)")

    def error(self, message: str):
        """argparse's refusals: one line naming the flag, exit 2."""
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


@dataclass(frozen=True)
class Command:
    """A sub-command: ``module`` (dotted name) holds ``add_arguments(parser)`` and ``run(args) -> int``; or, with
    ``commands``, a group of sub-commands (``dest`` names the namespace attribute that records which one ran).
    ``help`` defaults to the first line of the module's docstring."""

    name: str
    help: str = ""
    module: str = ""
    commands: tuple[Command, ...] = ()
    dest: str = ""


def add_commands(parser: argparse.ArgumentParser, commands: tuple[Command, ...], dest: str = "command") -> None:
    """One sub-parser per entry of ``commands`` (module docstrings as descriptions), groups recursively."""
    sub = parser.add_subparsers(dest=dest, required=True)
    for command in commands:
        if command.commands:
            group = sub.add_parser(command.name, help=command.help, description=command.help)
            add_commands(group, command.commands, command.dest or f"{command.name}_command")
            continue
        module = importlib.import_module(command.module)
        p = sub.add_parser(command.name, help=command.help or module.__doc__.strip().splitlines()[0],
                           description=module.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(p)
        p.set_defaults(func=module.run)


def quiet_worker_interrupts(*_) -> None:
    """The initializer of every worker process of a pool (``ProcessPoolExecutor(initializer=...)``): Ctrl-C reaches
    the whole process group; the command (the parent) ends with its one line (exit 130), and a worker ends at
    once, silently, instead of printing a ``KeyboardInterrupt`` traceback of its own (its scratch folder removed
    first: ``os._exit`` skips every exit handler)."""
    signal.signal(signal.SIGINT, _end_quietly)


def _end_quietly(*_) -> None:
    scratch = sys.modules.get("scenesplat_stereo.common.scratch")  # loaded where this worker may have a folder
    if scratch is not None:
        scratch.remove_own()
    os._exit(EXIT_INTERRUPTED)


def debugging(args: argparse.Namespace | None = None) -> bool:
    """``--debug`` was given, or ``STEREOGAUSSIANS_DEBUG`` is set to something other than "" or "0"."""
    return bool(getattr(args, "debug", False)) or os.environ.get(DEBUG_ENV, "") not in ("", "0")


def one_line(text: str) -> str:
    """A message as one line. An exception re-raised from a worker process (torch's DataLoader, a process
    pool) carries the worker's whole traceback: its last line, without the ``module.Class: `` prefix, is
    the original message."""
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    if any(line.startswith("Traceback (most recent call last)") or "Original Traceback" in line for line in lines):
        last = lines[-1]
        head, sep, rest = last.partition(": ")
        return rest if sep and " " not in head else last
    return " ".join(lines)


def os_error_message(e: OSError) -> str:
    """``<file>: <what happened> (<what to do>)`` for an OSError; the file first, as in every other message."""
    files = " -> ".join(str(f) for f in (e.filename, e.filename2) if f is not None)
    what = e.strerror or str(e) or type(e).__name__
    advice = _OS_ADVICE.get(e.errno)
    text = f"{files}: {what}" if files else what
    return f"{text} ({advice})" if advice and advice.lower() != what.lower() else text


def our_bug(e: BaseException) -> bool:
    """Whether a ``ValueError`` is our own bug rather than a refusal of bad input: raised implicitly (not by a
    ``raise`` statement) in a module of ours (unpacking, ``int()`` of our own text, ``list.index``), and not
    of an error class of ours. Refusals are raised on purpose: a subclass of ours, or ``raise ValueError(...)``."""
    if type(e).__module__.split(".")[0] in OUR_PACKAGES or e.__traceback__ is None:
        return False
    tb = e.__traceback__
    while tb.tb_next is not None:
        tb = tb.tb_next
    if str(tb.tb_frame.f_globals.get("__name__", "")).split(".")[0] not in OUR_PACKAGES:
        return False  # a library's ValueError: it names what it could not read
    return not linecache.getline(tb.tb_frame.f_code.co_filename, tb.tb_lineno).lstrip().startswith("raise")


def classify(e: BaseException, user_errors: Mapping[type, str] | None = None) -> tuple[int, str]:
    """(exit status, one-line message) for an exception that ended a command (see the module docstring)."""
    for cls, advice in (user_errors or {}).items():
        if isinstance(e, cls):
            return EXIT_USAGE, f"{advice} ({one_line(str(e))[:200]})"
    if isinstance(e, KeyboardInterrupt):
        return EXIT_INTERRUPTED, "interrupted" + (f": {one_line(str(e))}" if str(e) else "")
    if isinstance(e, OSError):
        return EXIT_USAGE, os_error_message(e)
    if isinstance(e, (ValueError, NotAvailable)) and not our_bug(e):
        return EXIT_USAGE, one_line(str(e)) or type(e).__name__
    if isinstance(e, tarfile.TarError):
        return EXIT_USAGE, f"corrupt tar archive: {one_line(str(e))}"
    return EXIT_INTERNAL, (f"internal error: {type(e).__name__}: {one_line(str(e))[:300]} (rerun with --debug or "
                           f"{DEBUG_ENV}=1 for the traceback, and please report it)")


class _WarningFormat(logging.Formatter):
    def __init__(self, command: str) -> None:
        super().__init__()
        self.command = command

    def format(self, record: logging.LogRecord) -> str:
        return f"{self.command}: {record.levelname.lower()}: {one_line(record.getMessage())}"


def run_command(parser: argparse.ArgumentParser, argv: list[str] | None = None,
                user_errors: Mapping[type, str] | None = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``), run ``args.func(args)`` and return the exit status;
    every error becomes one line on stderr (module docstring). argparse's refusals raise ``SystemExit(2)``."""
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    args = parser.parse_args(argv)
    args.command_argv = argv  # the command as typed, for advice that repeats it
    command = getattr(args, _COMMAND, parser.prog)
    debug = debugging(args)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_WarningFormat(command))
    root = logging.getLogger()
    root.addHandler(handler)
    level = root.level
    root.setLevel(min(level, logging.WARNING) if level else logging.WARNING)
    try:
        return int(args.func(args) or 0)
    except SystemExit:
        raise
    except BaseException as e:  # noqa: BLE001  (this is the one place every error ends)
        code, message = classify(e, user_errors)
        if debug:
            traceback.print_exc()
        print(f"{command}: error: {message}" if code != EXIT_INTERRUPTED else f"{command}: {message}",
              file=sys.stderr, flush=True)
        return code
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
