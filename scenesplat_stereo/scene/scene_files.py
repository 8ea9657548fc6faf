"""Scene files by format name: which module writes each, its file suffix, and reading any of them.

One owner per format (readers and writers side by side): ``gaussians`` (INRIA ``.ply``),
``compressed_ply`` (PlayCanvas ``.compressed.ply``), ``spz`` (Niantic ``.spz`` v3). ``load_scene`` tells
them apart by their first bytes, not by the name. docs/cli.md ``sgmodel predict --format`` and
docs/model.md "Scene files" give sizes, quantisation errors and the clients they were checked against.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from scenesplat_stereo.scene.compressed_ply import save_compressed_ply
from scenesplat_stereo.scene.gaussians import GaussianScene, PlyError, load_ply, save_ply
from scenesplat_stereo.scene.spz import load_spz, save_spz


@dataclass(frozen=True)
class SceneFormat:
    """A scene file format: name (as on the command line), file suffix, writer ``(scene, path, durable)``."""

    name: str
    suffix: str
    save: Callable[..., Path]
    description: str


FORMATS = {f.name: f for f in (
    SceneFormat("ply", ".ply", save_ply, "INRIA .ply, float32 (every 3DGS tool reads it)"),
    SceneFormat("compressed-ply", ".compressed.ply", save_compressed_ply,
                "PlayCanvas compressed .ply, 16 bytes + 1 byte per higher SH coefficient (SuperSplat)"),
    SceneFormat("spz", ".spz", save_spz, "Niantic .spz v3, gzip'd fixed point (Scaniverse, splat-transform)"),
)}


def save_scene(scene: GaussianScene, path: str | os.PathLike, format: str, durable: bool = True) -> Path:
    """Write ``scene`` to ``path`` in the named format (a key of ``FORMATS``), atomically."""
    if format not in FORMATS:
        raise ValueError(f"unknown scene format {format!r}; expected one of {', '.join(FORMATS)}")
    return FORMATS[format].save(scene, path, durable=durable)


def load_scene(path: str | os.PathLike) -> GaussianScene:
    """Read a scene in any of ``FORMATS`` (told apart by the file's first bytes); ``PlyError`` or ``SpzError``
    naming the file when it is none of them or broken."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise PlyError(f"{path}: cannot open ({e.strerror or e})") from None
    if magic[:2] == b"\x1f\x8b" or magic == b"NGSP":
        return load_spz(path)
    if magic.startswith(b"ply"):
        return load_ply(path)
    raise PlyError(f"{path}: neither a .ply nor a .spz file (first bytes {magic!r})")
