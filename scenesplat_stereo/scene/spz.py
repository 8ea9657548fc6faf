"""Niantic's ``.spz`` (versions 1 to 3): reader and writer, pure numpy and the standard library's gzip.

Written from the format description of the public nianticlabs/spz repository (README "File Format",
``load-spz.cc``). A v2/v3 file is one gzip stream holding a 16-byte little-endian header

    uint32 magic 0x5053474e ("NGSP"), uint32 version, uint32 numPoints,
    uint8 shDegree (0..3), uint8 fractionalBits, uint8 flags (0x1: antialiased), uint8 reserved (0)

followed by attribute blocks, each point after point:

* positions: 3 x 24-bit signed fixed point, little-endian, value = integer / 2^fractionalBits (version 1:
  3 x float16, which the reference still reads);
* alphas: uint8 round(255 opacity);
* colours: uint8 round(255 (0.15 f_dc + 0.5)) per channel (the SH DC coefficient, not SH_C0-scaled);
* scales: uint8 round(16 (ln s + 10)) per axis;
* rotations: v3 "smallest three": a little-endian uint32 whose bits 30-31 hold the index i of the largest
  |component| of the unit xyzw quaternion (made positive), then for each other component in xyzw order a
  sign bit and 9 bits of round(511 |c| / sqrt(1/2)); v1, v2: uint8 round(127.5 c + 127.5) for x, y, z with
  w = sqrt(max(0, 1 - x^2 - y^2 - z^2)) >= 0;
* SH (degree > 0): for each coefficient 1..K-1, the three colours (colour fastest), int8-like uint8
  round(128 f) + 128, quantised to buckets of 8 (degree 1, 5 bits) or 16 (degree 2 and 3, 4 bits) as the
  reference writer does; read back as (q - 128) / 128.

The reference writer rounds half away from zero (``std::round``) and clamps every byte to 0..255; so does
this one, so an encoded value inside a field's range is off by at most half a step: 2^-(fractionalBits+1)
metres in position (12 fractional bits, or fewer when the scene is too large for 24 bits), 1/32 in ln s
(range [-10, 5.94]), 1/(2 0.15 255) in f_dc (|f_dc| <= 3.33), 1/510 in opacity, and in SH (range [-1, 1))
half a step of 1/128 plus half a bucket: 4.5/128 (degree 1) or 8.5/128 (degrees 2 and 3).

Version 4 (the reference's newest, splat-transform's default) drops gzip: a 32-byte header (magic, version,
numPoints, shDegree, fractionalBits, flags, uint8 numStreams, uint32 tocByteOffset, 12 reserved bytes), optional
extensions up to tocByteOffset (flag 0x2; skipped, as the reference does without its extension support), a
table of numStreams (uint64 compressed size, uint64 uncompressed size), then one zstd frame per non-empty
block in the order above (positions, alphas, colours, scales, rotations, SH), the blocks as in version 3.
zstd is read through the system's libzstd (``ctypes``); without it version 4 is refused naming the converter.

Coordinates are stored as they are, without an axis change: that is what Niantic's own ``ply_to_spz``
(``CoordinateSystem::UNSPECIFIED``) and PlayCanvas' splat-transform write and read, so a scene keeps the
frame of its ``.ply`` (the README's default RUB applies to callers that declare a coordinate system).
This writer writes version 3, which every client reads: as one deflate stream (``gzip.compress``'s bytes), or
(``save_spz(..., parallel=True)``, the format ``spz-parallel``) deflated in pieces side by side, decoding to the same
bytes (docs/formats.md).
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import ctypes.util
import functools
import gzip
import math
import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.scene import row_tasks
from scenesplat_stereo.scene.gaussians import GaussianScene

#: "NGSP" read as a little-endian uint32.
MAGIC = 0x5053474E
#: The version this module writes, and the versions it reads.
WRITE_VERSION, READ_VERSIONS = 3, (1, 2, 3, 4)
#: Fractional bits of the fixed-point positions (the reference writer's 12: 1/4096 m steps).
FRACTIONAL_BITS = 12
#: Colours store f_dc scaled by this around 0.5 (the format's colorScale).
COLOR_SCALE = 0.15
#: SH quantisation: bits kept for degree 1 and for degrees 2 and 3 (the reference writer's defaults).
SH1_BITS, SH_REST_BITS = 5, 4
#: gzip level of the writer (zlib's default, as the reference writer's Z_DEFAULT_COMPRESSION).
GZIP_LEVEL = 6
#: Uncompressed bytes of a piece of ``save_spz(..., parallel=True)`` (pigz's 128 KiB), and deflate's window: the
#: bytes before a piece that prime its compressor.
DEFLATE_PIECE, DEFLATE_WINDOW = 1 << 17, 1 << 15
_HEADER = np.dtype([("magic", "<u4"), ("version", "<u4"), ("num_points", "<u4"), ("sh_degree", "u1"),
                    ("fractional_bits", "u1"), ("flags", "u1"), ("reserved", "u1")])
_NGSP_HEADER = np.dtype([("magic", "<u4"), ("version", "<u4"), ("num_points", "<u4"), ("sh_degree", "u1"),
                         ("fractional_bits", "u1"), ("flags", "u1"), ("num_streams", "u1"), ("toc", "<u4"),
                         ("reserved", "u1", 12)])
_SQRT1_2 = math.sqrt(0.5)


class SpzError(ValueError):
    """A ``.spz`` file that cannot be read (or a scene that cannot be written); names the file and field."""


def _fraction_bits(means: np.ndarray, path: Path) -> int:
    """Fractional bits of the 24-bit fixed-point positions: 12, fewer when the largest |coordinate| would not
    fit (|round(x 2^bits)| <= 2^23 - 1, rounded half away from zero as below)."""
    m = np.abs(means).max() if len(means) else 0.0
    bits = FRACTIONAL_BITS if m == 0 else min(FRACTIONAL_BITS, math.floor(math.log2((2**23 - 1) / m)))
    while bits >= 0 and math.floor(float(m) * 2.0**bits + 0.5) > 2**23 - 1:  # round half away is monotone
        bits -= 1
    if bits < 0:
        raise SpzError(f"{path}: positions up to {m:g} do not fit 24-bit fixed point (|x| < 2^23)")
    return bits


def _fill_bytes(out: np.ndarray, x: np.ndarray, scale: float, offset: float) -> None:
    """out (uint8) = clip(round half away from zero(x scale + offset), 0, 255), computed in float64 as the
    reference writer's ``std::round`` of its float products: for v = x scale + offset >= 0 that is
    floor(v + 1/2), and a v < 0 stores 0 either way (so clip(v + 1/2, 0, 255) truncated)."""
    v = np.multiply(x, scale, dtype=np.float64)
    v += offset
    v += 0.5
    np.clip(v, 0.0, 255.0, out=v)
    np.copyto(out, v, casting="unsafe")  # truncation: floor of a value >= 0


def _fill_positions(out: np.ndarray, means: np.ndarray, bits: int) -> None:
    """out uint8 [n, 9]: each coordinate round-half-away(x 2^bits) as 24-bit little-endian two's complement.
    x 2^bits + copysign(1/2) is exact in float64 for a float32 x (|x 2^bits| < 2^23), and truncation towards
    zero then rounds half away from zero."""
    y = np.multiply(means, 2.0**bits, dtype=np.float64)
    y += np.copysign(0.5, y)
    fixed = y.astype("<i4")
    out[:] = fixed.view(np.uint8).reshape(len(means), 3, 4)[:, :, :3].reshape(-1, 9)


def _fill_rotations(out: np.ndarray, quats: np.ndarray) -> None:
    """wxyz unit quaternions [n, 4] -> out uint8 [n, 4]: the smallest-three uint32 of version 3: bits 30-31 the
    index of the largest |component| (xyzw order), then each other component in xyzw order (the first in
    the highest bits) as a sign bit (of the component, made relative to a positive largest one) and 9 bits
    of floor(511 |c| / sqrt(1/2) + 1/2)."""
    q = quats[:, [1, 2, 3, 0]].astype(np.float64)  # xyzw, the format's order
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    n = len(q)
    largest = np.abs(q).argmax(1)
    negate = q[np.arange(n), largest] < 0
    word = np.floor(511.0 * np.abs(q) / _SQRT1_2 + 0.5).astype(np.uint32)
    word |= ((q < 0) ^ negate[:, None]).astype(np.uint32) << np.uint32(9)
    packed = largest.astype(np.uint32) << np.uint32(30)
    for j, shift in enumerate((20, 10, 0)):  # the j-th component other than the largest
        packed |= np.where(largest <= j, word[:, j + 1], word[:, j]) << np.uint32(shift)
    out[:] = packed.astype("<u4").view(np.uint8).reshape(n, 4)


def _fill_sh(out: np.ndarray, x: np.ndarray, bits: int) -> None:
    """out uint8 = the reference quantizeSH of x: q = round-half-away(128 x) + 128 snapped to a bucket of
    b = 2^(8 - bits) by floor((q + b/2) / b) b, clamped to 0..255.

    Computed as idx = floor(u), u = x 128/b + (128 + b/2 + 1/2)/b (exact in float64), which equals the
    bucket index for every x except an exact tie of a negative 128 x (round half away goes down there, so
    the index is ceil(u) - 1): those get u - 2^-30 first (a u that is not an integer lies at least 2^-25
    above the integer below it, so nothing else moves). Then min(idx b, 255) for idx in 0..256/b."""
    b = 1 << (8 - bits)
    u = np.multiply(x, 128.0 / b, dtype=np.float64)
    u += (128 + b // 2 + 0.5) / b
    u -= (x < 0) * 2.0**-30  # (a masked subtract, where=, is several times slower)
    np.clip(u, 0.0, 256 // b + 0.5, out=u)
    idx = u.astype(np.uint8)  # floor of u >= 0: 0..256/b
    idx_b = idx << np.uint8(8 - bits)  # idx b, 256 (the top index) wrapping to 0
    idx >>= np.uint8(bits)  # 1 for the top index only
    np.subtract(idx_b, idx, out=out, casting="unsafe")  # the top index's 0 - 1 wraps to 255


def _encoded_stream(scene: GaussianScene, path: Path) -> tuple[np.ndarray, Iterator[int]]:
    """The uncompressed version-3 stream (module docstring: header, positions, alphas, colours, scales,
    rotations, SH) as one uint8 array, and an iterator of how many of its leading bytes are final, yielded as
    each block is done. Every block's rows are quantised in tasks on the shared pool (``row_tasks``), all queued
    at once in file order, so a consumer (deflate) works on the stream's head while later blocks are quantised.
    The array is only complete once the iterator is exhausted."""
    n, k = len(scene), (scene.sh_degree + 1) ** 2
    bits = _fraction_bits(scene.means, path)
    header = np.zeros((), _HEADER)
    header[()] = (MAGIC, WRITE_VERSION, n, scene.sh_degree, bits, 0, 0)
    widths = [9, 1, 3, 3, 4, 3 * (k - 1)]
    stream = np.empty((_HEADER.itemsize + n * sum(widths),), np.uint8)
    stream[:_HEADER.itemsize] = np.frombuffer(header.tobytes(), np.uint8)
    ends = _HEADER.itemsize + np.cumsum([n * w for w in widths])
    blocks = np.split(stream[_HEADER.itemsize:], ends[:-1] - _HEADER.itemsize)
    positions, alphas, colours, scales, rotations, sh = (b.reshape(n, w) for b, w in zip(blocks, widths))
    sh = sh.reshape(n, k - 1, 3)
    fills = [
        lambda a, b: _fill_positions(positions[a:b], scene.means[a:b], bits),
        lambda a, b: _fill_bytes(alphas[a:b, 0], scene.opacities[a:b], 255.0, 0.0),
        lambda a, b: _fill_bytes(colours[a:b], scene.sh[a:b, 0, :], COLOR_SCALE * 255.0, 0.5 * 255.0),
        lambda a, b: _fill_bytes(scales[a:b], np.log(scene.scales[a:b].astype(np.float64)) + 10.0, 16.0, 0.0),
        lambda a, b: _fill_rotations(rotations[a:b], scene.quats[a:b]),
    ]
    if k > 1:
        def fill_sh(a: int, b: int) -> None:
            _fill_sh(sh[a:b, :3], scene.sh[a:b, 1:4], SH1_BITS)
            if k > 4:
                _fill_sh(sh[a:b, 3:], scene.sh[a:b, 4:], SH_REST_BITS)
        fills.append(fill_sh)
    tasks = [row_tasks.submit_rows(fill, n) for fill in fills]

    def ready() -> Iterator[int]:
        yield _HEADER.itemsize
        try:
            for end, futures in zip(ends, tasks):
                row_tasks.wait_all(futures)
                yield int(end)
        finally:
            for futures in tasks:  # an abandoned stream: let its tasks end before the arrays go
                concurrent.futures.wait(futures)

    return stream, ready()


def encode_spz(scene: GaussianScene, path: str | os.PathLike = "<memory>") -> bytes:
    """The uncompressed version-3 bytes (header and blocks) of ``scene`` (module docstring). The header's flags
    are 0: not antialiased (bit 0x1 marks scenes trained with mip-splatting's filter; ours render in
    gsplat's "classic" mode)."""
    stream, ready = _encoded_stream(scene, Path(path))
    for _ in ready:
        pass
    return stream.tobytes()


def _gzip_header() -> bytes:
    """The 10 bytes ``gzip.compress(..., compresslevel=GZIP_LEVEL, mtime=0)`` starts with in this Python (they
    do not depend on the data; the OS byte, the 10th, is zlib's 3 on Linux up to Python 3.12 and 255 from
    3.13 on, CPython gh-112346)."""
    return gzip.compress(b"", compresslevel=GZIP_LEVEL, mtime=0)[:10]


def _deflate_piece(stream: np.ndarray, start: int, end: int) -> bytes:
    """Raw deflate at ``GZIP_LEVEL`` of stream[start:end], primed with the 32 KiB before it as zlib's dictionary
    (what a one-stream deflate could refer back to) and ended by a sync flush (an empty stored block: the output
    ends on a byte boundary, the stream left open), or by the final block where ``end`` is the stream's: the
    pieces in order are one raw deflate stream of the whole (pigz's method). zlib runs without the GIL."""
    zdict = {"zdict": stream[max(0, start - DEFLATE_WINDOW):start]} if start else {}
    deflate = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, -zlib.MAX_WBITS, **zdict)
    last = end == len(stream)
    return deflate.compress(stream[start:end]) + deflate.flush(zlib.Z_FINISH if last else zlib.Z_SYNC_FLUSH)


def save_spz(scene: GaussianScene, path: str | os.PathLike, durable: bool = True, parallel: bool = False) -> Path:
    """Write ``scene`` as a version-3 ``.spz``, atomically. Returns the path.

    By default the bytes are ``gzip.compress(encode_spz(scene), compresslevel=GZIP_LEVEL, mtime=0)``'s: its
    header, one raw deflate stream at that level (zlib's output does not depend on how its input is split between
    calls) and the CRC-32 and length trailer. The stream is deflated block by block while the later blocks are
    quantised; that one deflate is the writer's serial step (about 80% of its CPU time).

    ``parallel``: the same gzip header, stream and trailer, but the stream deflated in pieces of
    ``DEFLATE_PIECE`` bytes in tasks of the shared pool (``_deflate_piece``), each queued as soon as its bytes
    are quantised: every gzip reader decodes the same bytes, the file is a little larger (each piece starts a
    new deflate block; docs/formats.md) and its compressed bytes differ from the one-stream writer's."""
    path = Path(path)
    stream, ready = _encoded_stream(scene, path)
    crc, done, pieces = 0, 0, []
    try:
        if parallel:
            pool, queued = row_tasks.pool(), 0
            for end in ready:
                crc, done = zlib.crc32(stream[done:end], crc), end
                while queued + DEFLATE_PIECE < end or (queued < end == len(stream)):
                    stop = min(queued + DEFLATE_PIECE, len(stream))
                    pieces.append(pool.submit(_deflate_piece, stream, queued, stop))
                    queued = stop
            deflated = [f.result() for f in pieces]
        else:
            deflate = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, -zlib.MAX_WBITS)
            deflated = []
            for end in ready:
                deflated.append(deflate.compress(stream[done:end]))
                crc, done = zlib.crc32(stream[done:end], crc), end
            deflated.append(deflate.flush())
    finally:  # after an error or an interrupt, no piece is left running on the stream
        for f in pieces:
            f.cancel()
        concurrent.futures.wait(pieces)
    atomic_write_bytes(path, [_gzip_header(), *deflated, struct.pack("<II", crc, len(stream) & 0xFFFFFFFF)],
                       durable=durable)
    return path


def _unpack_rotations(raw: np.ndarray, version: int) -> np.ndarray:
    """uint8 [N, 4] (v3) or [N, 3] (v1, v2) -> unit wxyz float64 [N, 4]."""
    n = len(raw)
    xyzw = np.empty((n, 4), dtype=np.float64)
    if version < 3:
        xyzw[:, :3] = raw.astype(np.float64) / 127.5 - 1.0
        xyzw[:, 3] = np.sqrt(np.maximum(0.0, 1.0 - (xyzw[:, :3] ** 2).sum(1)))
    else:
        comp = np.ascontiguousarray(raw).view("<u4").reshape(n).astype(np.uint32)
        largest = (comp >> np.uint32(30)).astype(np.int64)
        for i in range(3, -1, -1):  # the last component written sits in the lowest bits
            mag = (comp & np.uint32(511)).astype(np.float64)
            value = np.where((comp >> np.uint32(9)) & np.uint32(1), -1.0, 1.0) * _SQRT1_2 * mag / 511.0
            here = largest != i
            xyzw[here, i] = value[here]
            comp = np.where(here, comp >> np.uint32(10), comp)
        others = np.where(np.arange(4)[None] == largest[:, None], 0.0, xyzw)
        xyzw[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - (others**2).sum(1)))
    norm = np.linalg.norm(xyzw, axis=1, keepdims=True)
    xyzw = np.where(norm > 0, xyzw / np.where(norm > 0, norm, 1.0), [0.0, 0.0, 0.0, 1.0])
    return xyzw[:, [3, 0, 1, 2]]


def spz_header(path: str | os.PathLike) -> tuple[int, int]:
    """(numPoints, shDegree) of a ``.spz`` from its header (the first 16 bytes of the gzip stream, or of the
    version-4 file, which start alike)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(_HEADER.itemsize)
        if data[:4] != b"NGSP":
            with gzip.open(path) as f:
                data = f.read(_HEADER.itemsize)
    except OSError as e:  # also gzip.BadGzipFile: no .spz at all
        raise SpzError(f"{path}: not a .spz header ({e.strerror or e})") from None
    except (EOFError, zlib.error) as e:
        raise SpzError(f"{path}: corrupt gzip stream ({e})") from None
    if len(data) < _HEADER.itemsize:
        raise SpzError(f"{path}: header truncated ({len(data)} of {_HEADER.itemsize} bytes)")
    h = np.frombuffer(data, _HEADER, 1)[0]
    if int(h["magic"]) != MAGIC or int(h["version"]) not in READ_VERSIONS or int(h["sh_degree"]) > 3:
        raise SpzError(f"{path}: header magic {int(h['magic']):#x}, version {int(h['version'])}, shDegree "
                       f"{int(h['sh_degree'])}: not a .spz this reads (versions {READ_VERSIONS}, SH 0..3)")
    return int(h["num_points"]), int(h["sh_degree"])


def load_spz(path: str | os.PathLike) -> GaussianScene:
    """Read a version 1 to 4 ``.spz`` into a ``GaussianScene``; ``SpzError`` naming the file and field."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise SpzError(f"{path}: cannot open ({e.strerror or e})") from None
    if raw[:4] == b"NGSP":
        return _decode(path, *_ngsp_blocks(raw, path))
    if raw[:2] != b"\x1f\x8b":
        raise SpzError(f"{path}: not a .spz file (neither gzip nor 'NGSP' magic at the start)")
    try:
        data = gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as e:
        raise SpzError(f"{path}: corrupt gzip stream ({e})") from None
    if len(data) < _HEADER.itemsize:
        raise SpzError(f"{path}: header truncated ({len(data)} of {_HEADER.itemsize} bytes)")
    h = np.frombuffer(data, _HEADER, 1)[0]
    if int(h["magic"]) != MAGIC:
        raise SpzError(f"{path}: header magic is {int(h['magic']):#x}, expected {MAGIC:#x} ('NGSP')")
    version, n, degree = int(h["version"]), int(h["num_points"]), int(h["sh_degree"])
    if version not in READ_VERSIONS:
        raise SpzError(f"{path}: header version {version} is not supported (reads {READ_VERSIONS})")
    if degree > 3:
        raise SpzError(f"{path}: header shDegree {degree}: SH degree 0..3 supported")
    sizes = _block_sizes(version, degree)
    need = _HEADER.itemsize + n * sum(sizes.values())
    if len(data) < need:
        raise SpzError(f"{path}: body truncated: header numPoints {n} needs {need} bytes, the stream has "
                       f"{len(data)}")
    blocks, offset = {}, _HEADER.itemsize
    for name, size in sizes.items():
        blocks[name] = np.frombuffer(data, np.uint8, n * size, offset).reshape(n, size)
        offset += n * size
    return _decode(path, version, n, degree, int(h["fractional_bits"]), blocks)


def _block_sizes(version: int, degree: int) -> dict[str, int]:
    """Bytes a point of each block, in file order."""
    return {"positions": 9 if version > 1 else 6, "alphas": 1, "colours": 3, "scales": 3,
            "rotations": 4 if version >= 3 else 3, "sh": 3 * ((degree + 1) ** 2 - 1)}


@functools.cache
def _libzstd() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("zstd")
    if name is None:
        return None
    lib = ctypes.CDLL(name)
    lib.ZSTD_decompress.restype = ctypes.c_size_t
    lib.ZSTD_decompress.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p, ctypes.c_size_t]
    lib.ZSTD_isError.restype, lib.ZSTD_isError.argtypes = ctypes.c_uint, [ctypes.c_size_t]
    lib.ZSTD_getErrorName.restype, lib.ZSTD_getErrorName.argtypes = ctypes.c_char_p, [ctypes.c_size_t]
    return lib


def _ngsp_blocks(raw: bytes, path: Path) -> tuple[int, int, int, int, dict[str, np.ndarray]]:
    """(version, numPoints, shDegree, fractionalBits, blocks) of a version-4 file (module docstring)."""
    if len(raw) < _NGSP_HEADER.itemsize:
        raise SpzError(f"{path}: header truncated ({len(raw)} of {_NGSP_HEADER.itemsize} bytes)")
    h = np.frombuffer(raw, _NGSP_HEADER, 1)[0]
    version, n, degree, streams, toc = (int(h[k]) for k in ("version", "num_points", "sh_degree", "num_streams",
                                                              "toc"))
    if version != 4:
        raise SpzError(f"{path}: header version {version} is not supported with 'NGSP' magic (version 4)")
    if degree > 3 or n == 0:
        raise SpzError(f"{path}: header numPoints {n}, shDegree {degree}: need >= 1 point and SH degree 0..3")
    sizes = {k: v for k, v in _block_sizes(version, degree).items() if v}
    end = toc + 16 * streams
    if streams != len(sizes) or toc < _NGSP_HEADER.itemsize or end > len(raw):
        raise SpzError(f"{path}: header numStreams {streams} / tocByteOffset {toc}: expected {len(sizes)} "
                       f"streams and a table inside the file's {len(raw)} bytes")
    table = np.frombuffer(raw, "<u8", 2 * streams, toc).reshape(streams, 2)
    if int(table[:, 0].sum()) != len(raw) - end:
        raise SpzError(f"{path}: stream table: compressed sizes add up to {int(table[:, 0].sum())} bytes, the "
                       f"file has {len(raw) - end} after the table (truncated?)")
    lib = _libzstd()
    if lib is None:
        raise SpzError(f"{path}: .spz version 4 (zstd streams) needs the zstd library (libzstd), not found here; "
                       f"install it or convert: `splat-transform {path.name} --spz-version 3 out.spz`")
    blocks, offset = {}, end
    for (name, size), (packed, unpacked) in zip(sizes.items(), table.tolist()):
        if unpacked != n * size:
            raise SpzError(f"{path}: stream {name}: {unpacked} bytes uncompressed, numPoints {n} needs {n * size}")
        out = np.empty(n * size, np.uint8)
        got = lib.ZSTD_decompress(out.ctypes.data, out.size, raw[offset:offset + packed], packed)
        if lib.ZSTD_isError(got) or got != out.size:
            why = lib.ZSTD_getErrorName(got).decode() if lib.ZSTD_isError(got) else f"{got} bytes"
            raise SpzError(f"{path}: stream {name}: corrupt zstd data ({why})")
        blocks[name], offset = out.reshape(n, size), offset + packed
    blocks.setdefault("sh", np.zeros((n, 0), np.uint8))
    return version, n, degree, int(h["fractional_bits"]), blocks


def _decode(path: Path, version: int, n: int, degree: int, fbits: int, blocks: dict[str, np.ndarray]) -> GaussianScene:
    """The scene of the raw blocks [N, bytes] (module docstring)."""
    k = (degree + 1) ** 2
    if version == 1:
        means = np.ascontiguousarray(blocks["positions"]).view("<f2").astype(np.float32)
        if not np.isfinite(means).all():
            raise SpzError(f"{path}: positions: {int((~np.isfinite(means)).any(1).sum())} float16 positions "
                           "are inf or NaN")
    else:
        p = blocks["positions"].reshape(n, 3, 3).astype(np.int32)
        fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
        fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
        means = (fixed / 2.0 ** fbits).astype(np.float32)
    sh = np.empty((n, k, 3), np.float32)
    sh[:, 0] = (blocks["colours"].astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE
    sh[:, 1:] = ((blocks["sh"].astype(np.float64) - 128.0) / 128.0).reshape(n, k - 1, 3)
    scene = GaussianScene(means,
                          _unpack_rotations(blocks["rotations"], version).astype(np.float32),
                          np.exp(blocks["scales"].astype(np.float64) / 16.0 - 10.0).astype(np.float32),
                          (blocks["alphas"][:, 0] / 255.0).astype(np.float32), sh, degree)
    return scene
