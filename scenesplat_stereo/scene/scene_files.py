"""Scene files by format name: which module writes each, its file suffix, and reading any of them.

One owner per format (readers and writers side by side): ``gaussians`` (INRIA ``.ply``), ``compressed_ply``
(PlayCanvas ``.compressed.ply``), ``spz`` (Niantic ``.spz`` v1-v3), ``sog`` (PlayCanvas SOG: a ``.sog`` zip or
``meta.json`` + WebP images), ``lod`` (streamed SOG: ``lod-meta.json`` and SOG units, read at one level),
``splat`` (antimatter15 ``.splat``, read only). ``load_scene`` tells them apart by their first bytes, except
the two that have none to tell: JSON files by name (``meta.json``, ``lod-meta.json``, or a folder holding
one) and ``.splat`` by suffix (its size a multiple of 32 bytes). docs/cli.md ``sgmodel predict --format`` and
docs/formats.md give sizes, quantisation errors and the clients they were checked against.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from scenesplat_stereo.scene.compressed_ply import save_compressed_ply
from scenesplat_stereo.scene.gaussians import GaussianScene, PlyError, load_ply, read_ply_header, save_ply
from scenesplat_stereo.scene.lod import NAME as LOD_META
from scenesplat_stereo.scene.lod import load_lod, lod_info
from scenesplat_stereo.scene.sog import SogSource, load_sog, save_sog
from scenesplat_stereo.scene.splat import load_splat, splat_count
from scenesplat_stereo.scene.spz import load_spz, save_spz, spz_header


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
    SceneFormat("spz-parallel", ".spz", functools.partial(save_spz, parallel=True),
                "the same .spz, its gzip stream deflated in 128 KiB pieces side by side (pigz's method): the same "
                "decoded bytes, 0.01-0.03 percent larger, several times faster on many cores"),
    SceneFormat("sog", ".sog", save_sog, "PlayCanvas SOG v2, zip of lossless WebP images and codebooks "
                "(SuperSplat, PlayCanvas engine, splat-transform)"),
)}
#: Suffixes of the single-file scenes ``load_scene`` reads (``.compressed.ply`` is a ``.ply``), and the names
#: of the JSON files that stand for a scene (a SOG's ``meta.json``, a streamed scene's ``lod-meta.json``).
SCENE_SUFFIXES, SCENE_JSON = (".ply", ".spz", ".sog", ".splat"), (LOD_META, "meta.json")


def save_scene(scene: GaussianScene, path: str | os.PathLike, format: str, durable: bool = True) -> Path:
    """Write ``scene`` to ``path`` in the named format (a key of ``FORMATS``), atomically."""
    if format not in FORMATS:
        raise ValueError(f"unknown scene format {format!r}; expected one of {', '.join(FORMATS)}")
    return FORMATS[format].save(scene, path, durable=durable)


def scene_kind(path: str | os.PathLike) -> str:
    """Which reader reads ``path``: "ply", "spz", "sog", "lod" or "splat" (first bytes, else the name; a folder by
    the ``lod-meta.json`` or ``meta.json`` it holds). ``PlyError`` naming the file when it is none of them."""
    path = Path(path)
    if path.is_dir():
        found = next((name for name in SCENE_JSON if (path / name).is_file()), None)
        if found is None:
            raise PlyError(f"{path}: a folder without {' or '.join(SCENE_JSON)} (a streamed or unbundled SOG)")
        path = path / found
    if path.name.endswith(LOD_META):
        return "lod"
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise PlyError(f"{path}: cannot open ({e.strerror or e})") from None
    if path.suffix == ".json":
        return "sog"
    if magic[:2] == b"\x1f\x8b" or magic == b"NGSP":
        return "spz"
    if magic.startswith(b"ply"):
        return "ply"
    if magic == b"PK\x03\x04":
        return "sog"
    if path.suffix in (".splat", ".ply", ".spz", ".sog"):  # no magic, or a broken file: its reader says what
        return {".splat": "splat", ".ply": "ply", ".spz": "spz", ".sog": "sog"}[path.suffix]
    raise PlyError(f"{path}: not a scene file this reads (.ply, .compressed.ply, .spz, .sog, meta.json, "
                   f"lod-meta.json, .splat; first bytes {magic!r})")


def load_scene(path: str | os.PathLike, strict: bool = False, lod: int = 0) -> GaussianScene:
    """Read a scene in any format ``scene_kind`` names; errors are ``ValueError`` subclasses (``PlyError``,
    ``SpzError``, ``SogError``, ``LodError``, ``SplatError``) naming the file and field. ``strict`` is
    ``load_ply``'s (refuse rows it would drop; the other readers always refuse them); ``lod`` the level of a
    streamed scene (0, the finest, by default)."""
    kind = scene_kind(path)
    if kind == "ply":
        return load_ply(path, strict=strict)
    if kind == "lod":
        return load_lod(path, lod)
    return {"spz": load_spz, "sog": load_sog, "splat": load_splat}[kind](path)


def scene_info(path: str | os.PathLike, lod: int = 0) -> tuple[int, int]:
    """(Gaussians, SH degree) of a scene file read from its header only (the ``.ply`` header, the SOG and
    streamed scene's JSON, the ``.spz`` header, the ``.splat``'s size); errors as ``load_scene``'s."""
    kind = scene_kind(path)
    if kind == "ply":
        header = read_ply_header(path)
        return header.num_gaussians, header.sh_degree
    if kind == "lod":
        return lod_info(path, lod)
    if kind == "sog":
        src = SogSource(path)
        return src.count(), src.sh_degree()
    if kind == "splat":
        return splat_count(path), 0
    return spz_header(path)
