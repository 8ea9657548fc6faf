"""The PLY container of Gaussian scene files: header and elements, as the INRIA layout
(``scenesplat_stereo.scene.gaussians``) and the PlayCanvas compressed one (``scenesplat_stereo.scene.compressed_ply``)
both read them, and the conventions every layout shares (``SH_C0``; the SH degree of a count of ``f_rest_*``).

``read_ply_header`` parses and checks a header (ascii, binary_little_endian, binary_big_endian; elements with
scalar properties of any numeric type, list properties only in elements that are skipped) and tells the
layout apart (an element ``chunk``: compressed); ``read_elements`` reads the wanted elements as structured
arrays; ``columns`` takes named properties as float64. Bad files raise ``PlyError`` naming the file and the
field; extra bytes after the last element are a ``PlyRepairWarning``.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.harmonics import SH_C0  # noqa: F401 (band 0: colour = 0.5 + SH_C0 * f_dc; re-exported)

#: Number of ``f_rest_*`` properties -> SH degree (3 channels x ((d+1)^2 - 1) coefficients).
SH_DEGREE_OF_REST_COUNT = {0: 0, 9: 1, 24: 2, 45: 3}
_HEADER_LIMIT = 1 << 20

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


class PlyError(ValueError):
    """A ``.ply`` file that cannot be read as a Gaussian scene; the message names the file and the field."""


class PlyRepairWarning(UserWarning):
    """Rows were dropped while loading a ``.ply`` (the message names the file and the counts per reason)."""


@dataclass(frozen=True)
class PlyElement:
    """One header element: name, row count, properties as (name, numpy type code), (name, None) for lists."""

    name: str
    count: int
    properties: tuple[tuple[str, str | None], ...]

    def names(self) -> list[str]:
        return [p for p, _ in self.properties]

    def dtype(self, byte_order: str) -> np.dtype:
        return np.dtype([(p, byte_order + t) for p, t in self.properties])  # type: ignore[operator]

    def has_lists(self) -> bool:
        return any(t is None for _, t in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """A parsed ``.ply`` header; ``layout`` is "inria" or "compressed", ``sh_degree`` follows from it."""

    path: Path
    format: str
    elements: tuple[PlyElement, ...]
    body_offset: int
    layout: str
    sh_degree: int

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)

    @property
    def num_gaussians(self) -> int:
        """Rows of element ``vertex`` (before any row is dropped by ``load_ply``)."""
        return self.element("vertex").count  # type: ignore[union-attr]


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """Parse and check the header of a Gaussian ``.ply`` (cheap: the body is not read)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(_HEADER_LIMIT)
    except OSError as e:
        raise PlyError(f"{path}: cannot open ({e.strerror or e})") from e
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        raise PlyError(f"{path}: not a PLY file (it does not start with the 'ply' magic line)")
    end = head.find(b"\nend_header")
    if end < 0:
        raise PlyError(f"{path}: no 'end_header' line within the first {_HEADER_LIMIT} bytes")
    body = end + len(b"\nend_header")
    if head[body:body + 1] != b"\n" and head[body:body + 2] != b"\r\n":
        raise PlyError(f"{path}: malformed 'end_header' line")
    body += 2 if head[body:body + 2] == b"\r\n" else 1
    try:
        lines = head[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError as e:
        raise PlyError(f"{path}: header is not ASCII text") from e
    fmt, elements, current = None, [], None
    for i, line in enumerate(lines, start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3:
            if words[1] not in _FORMATS:
                raise PlyError(f"{path}: unsupported format '{words[1]}' (header line {i})")
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            if words[1] in (e[0] for e in elements):
                raise PlyError(f"{path}: element '{words[1]}' is declared twice (header line {i})")
            current = [words[1], int(words[2]), []]
            elements.append(current)
        elif words[0] == "property" and current is not None and len(words) in (3, 5):
            if len(words) == 5 and words[1] != "list":
                raise PlyError(f"{path}: malformed property line {i}: {line!r}")
            name, typ = words[-1], words[-2]
            if typ not in _PLY_TYPES or (len(words) == 5 and words[2] not in _PLY_TYPES):
                raise PlyError(f"{path}: element '{current[0]}' property '{name}' has unknown type '{typ}'")
            if name in (p for p, _ in current[2]):
                raise PlyError(f"{path}: element '{current[0]}' property '{name}' is declared twice")
            current[2].append((name, None if len(words) == 5 else _PLY_TYPES[typ]))
        else:
            raise PlyError(f"{path}: malformed header line {i}: {line!r}")
    if fmt is None:
        raise PlyError(f"{path}: header has no 'format' line")
    elems = tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements)
    by_name = {e.name: e for e in elems}
    if "vertex" not in by_name:
        raise PlyError(f"{path}: no element 'vertex'")
    layout = "compressed" if "chunk" in by_name else "inria"
    if layout == "compressed":
        rest = len(by_name["sh"].properties) if "sh" in by_name else 0
    else:
        rest = sum(p.startswith("f_rest_") for p in by_name["vertex"].names())
    if rest not in SH_DEGREE_OF_REST_COUNT:
        raise PlyError(f"{path}: {rest} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0..3)")
    return PlyHeader(path, fmt, elems, body, layout, SH_DEGREE_OF_REST_COUNT[rest])


def read_elements(header: PlyHeader, wanted: set[str]) -> dict[str, np.ndarray]:
    """Structured arrays of the ``wanted`` elements (their properties must be scalars)."""
    path, out = header.path, {}
    last = max(i for i, e in enumerate(header.elements) if e.name in wanted)
    for e in header.elements[:last + 1]:
        if e.has_lists() and (e.name in wanted or header.format != "ascii"):
            raise PlyError(f"{path}: element '{e.name}' has list properties, which are not supported here")
    if header.format == "ascii":
        with open(path, "rb") as f:
            f.seek(header.body_offset)
            lines = [ln for ln in f.read().split(b"\n") if ln.strip()]
        row = 0
        for e in header.elements[:last + 1]:
            block = lines[row:row + e.count]
            if len(block) < e.count:
                raise PlyError(f"{path}: body truncated: element '{e.name}' needs {e.count} lines, "
                               f"found {len(block)}")
            row += e.count
            if e.name in wanted:
                out[e.name] = _parse_ascii(path, e, block)
        if last == len(header.elements) - 1 and row < len(lines):
            e = header.elements[last]
            raise PlyError(f"{path}: element '{e.name}' declares {e.count} rows but the body has "
                           f"{len(lines) - row} more non-empty lines after them")
        return out
    size, offset = path.stat().st_size, header.body_offset
    with open(path, "rb") as f:
        for e in header.elements[:last + 1]:
            dtype = e.dtype(_FORMATS[header.format])  # type: ignore[arg-type]
            need = dtype.itemsize * e.count
            if offset + need > size:
                raise PlyError(f"{path}: body truncated: element '{e.name}' needs {need} bytes at offset "
                               f"{offset}, the file has {max(size - offset, 0)}")
            if e.name in wanted:
                f.seek(offset)
                out[e.name] = np.fromfile(f, dtype=dtype, count=e.count)
            offset += need
    rest = header.elements[last + 1:]
    if offset < size and not any(e.has_lists() for e in rest):
        extra = size - offset - sum(e.dtype("<").itemsize * e.count for e in rest)
        if extra > 0:
            warnings.warn(f"{path}: {extra} bytes after the last element were ignored", PlyRepairWarning,
                          stacklevel=3)
    return out


def _parse_ascii(path: Path, e: PlyElement, block: list[bytes]) -> np.ndarray:
    rows = [ln.split() for ln in block]
    for i, r in enumerate(rows):
        if len(r) != len(e.properties):
            raise PlyError(f"{path}: element '{e.name}' row {i} has {len(r)} values, expected "
                           f"{len(e.properties)}")
    try:
        values = np.array(rows, dtype=np.float64).reshape(len(rows), len(e.properties))
    except ValueError as err:
        raise PlyError(f"{path}: element '{e.name}' has a non-numeric value ({err})") from err
    arr = np.empty(len(rows), dtype=e.dtype("="))
    for j, (name, _) in enumerate(e.properties):
        arr[name] = values[:, j]
    return arr


def columns(path: Path, arr: np.ndarray, element: str, names: list[str]) -> np.ndarray:
    """float64 [N, len(names)] of the named properties; a missing one is a PlyError naming it."""
    missing = [n for n in names if n not in (arr.dtype.names or ())]
    if missing:
        raise PlyError(f"{path}: element '{element}' lacks required properties {', '.join(missing)}")
    out = np.empty((len(arr), len(names)), dtype=np.float64)
    for j, n in enumerate(names):
        out[:, j] = arr[n]
    return out
