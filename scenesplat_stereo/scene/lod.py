"""Streamed SOG scenes (PlayCanvas levels of detail): ``lod-meta.json`` and its SOG units, read at one level.

Written from the format as PlayCanvas' splat-transform 3.7.0 reads it (``readLodSource``). ``lod-meta.json``
holds ``lodLevels`` (L >= 1), ``filenames`` (paths, relative to it, of SOG units: ``meta.json`` files or
``.sog`` bundles), optional ``version`` (1) and ``counts`` (Gaussians per level), and ``tree``: nodes with
optional ``children`` and ``lods`` ``{"<level>": {"file": i, "offset": o, "count": c}}``, meaning rows
o .. o + c - 1 of unit ``filenames[i]`` belong to that level. Level 0 is the finest (most Gaussians).

``load_lod(path, level)`` reads every unit referenced at ``level`` (each decoded once by
``scenesplat_stereo.scene.sog``) and keeps the referenced rows, units in file-index order and rows in offset order
within a unit (splat-transform's order). Ranges that overlap or run past a unit's count, and ``counts`` that
do not match the tree, are refused.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.gaussians import GaussianScene, decoded_scene
from scenesplat_stereo.scene.sog import SogError, SogSource, decode_sog

NAME = "lod-meta.json"


class LodError(SogError):
    """A streamed scene that cannot be read; names ``lod-meta.json`` (or the unit) and the field."""


def read_lod_meta(path: str | os.PathLike) -> tuple[Path, dict, dict[int, dict[int, list[tuple[int, int]]]]]:
    """(path of lod-meta.json, its JSON, {level: {file index: [(offset, count), ...]}}) of a streamed scene
    (``path`` is the file or its folder); ``LodError`` naming the field when it is malformed."""
    path = Path(path)
    if path.is_dir():
        path = path / NAME
    try:
        meta = json.loads(path.read_bytes())
    except OSError as e:
        raise LodError(f"{path}: cannot read ({e.strerror or e})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise LodError(f"{path}: not JSON ({e})") from None
    if not isinstance(meta, dict):
        raise LodError(f"{path}: expected a JSON object")
    if meta.get("version") not in (None, 1):
        raise LodError(f"{path}: version: {meta.get('version')!r} is not supported (1)")
    levels, names = meta.get("lodLevels"), meta.get("filenames")
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 1:
        raise LodError(f"{path}: lodLevels: expected a whole number >= 1, got {levels!r}")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise LodError(f"{path}: filenames: expected a list of file names")
    refs: dict[int, dict[int, list[tuple[int, int]]]] = {}
    stack = [("tree", meta.get("tree"))]
    while stack:
        where, node = stack.pop()
        if not isinstance(node, dict) or not isinstance(node.get("children", []), list) \
                or not isinstance(node.get("lods", {}), dict):
            raise LodError(f"{path}: {where}: expected a node object (children a list, lods an object)")
        for key, ref in node.get("lods", {}).items():
            ok = isinstance(ref, dict) and all(isinstance(ref.get(k), int) and not isinstance(ref.get(k), bool)
                                               and ref.get(k) >= 0 for k in ("file", "offset", "count"))
            if not (key.isdigit() and int(key) < levels and ok and ref["file"] < len(names)):
                raise LodError(f"{path}: {where}.lods[{key!r}]: expected a level < lodLevels and "
                               f"{{file < {len(names)}, offset >= 0, count >= 0}}, got {ref!r}")
            refs.setdefault(int(key), {}).setdefault(ref["file"], []).append((ref["offset"], ref["count"]))
        stack += [(f"{where}.children[{i}]", c) for i, c in enumerate(node.get("children", []))][::-1]
    counts = meta.get("counts")
    if counts is not None:
        found = [sum(c for rs in refs.get(level, {}).values() for _, c in rs) for level in range(levels)]
        if counts != found:
            raise LodError(f"{path}: counts: {counts!r} but the tree references {found}")
    return path, meta, refs


def lod_info(path: str | os.PathLike, level: int = 0) -> tuple[int, int]:
    """(Gaussians at ``level``, SH degree of its first unit) from the JSON files only."""
    lod_path, meta, refs = _level(path, level)
    first = SogSource(lod_path.parent / meta["filenames"][min(refs)])
    return sum(c for rs in refs.values() for _, c in rs), first.sh_degree()


def _level(path: str | os.PathLike, level: int) -> tuple[Path, dict, dict[int, list[tuple[int, int]]]]:
    lod_path, meta, refs = read_lod_meta(path)
    if not 0 <= level < meta["lodLevels"] or not refs.get(level):
        raise LodError(f"{lod_path}: level {level}: no Gaussians at that level (lodLevels "
                       f"{meta['lodLevels']}; 0 is the finest)")
    return lod_path, meta, refs[level]


def load_lod(path: str | os.PathLike, level: int = 0) -> GaussianScene:
    """The Gaussians of one level (default 0, the finest) of a streamed SOG scene (module docstring)."""
    lod_path, meta, refs = _level(path, level)
    parts, degrees = [], set()
    for index in sorted(refs):
        src = SogSource(lod_path.parent / meta["filenames"][index])
        *arrays, degree = decode_sog(src)
        n, rows, end = len(arrays[0]), [], 0
        for offset, count in sorted(refs[index]):
            if offset < end or offset + count > n:
                raise LodError(f"{lod_path}: level {level} references rows {offset}..{offset + count - 1} of "
                               f"{src.name} ({n} Gaussians), overlapping or past its end")
            rows.append(np.arange(offset, offset + count))
            end = offset + count
        keep = np.concatenate(rows)
        parts.append([a[keep] for a in arrays])
        degrees.add(degree)
    if len(degrees) > 1:
        raise LodError(f"{lod_path}: level {level}: units of SH degrees {sorted(degrees)} (one expected)")
    joined = [np.concatenate(column) for column in zip(*parts)]
    return decoded_scene(f"{lod_path} (level {level})", LodError, *joined, degrees.pop())
