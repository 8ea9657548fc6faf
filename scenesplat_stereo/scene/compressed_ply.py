"""The PlayCanvas / SuperSplat compressed ``.ply``: its reader (``load_ply`` dispatches here) and writer.

Layout (as PlayCanvas' splat-transform writes it and the SuperSplat viewer reads it):

* element ``chunk``, one row per 256 splats (in file order): float ``min_/max_`` x, y, z (the chunk's
  box), ``min_/max_scale_`` x, y, z (its box of log scales, clamped to [-20, 20] by the writer), optional
  ``min_/max_`` r, g, b (its colour range);
* element ``vertex``, uint32 ``packed_position`` (11-10-11 bit unorm within the chunk box),
  ``packed_rotation`` (bits 30-31: index of the largest |component| of the unit wxyz quaternion, made
  positive; then the three others in order, 10 bits each, as unorm(c / sqrt(2) + 0.5)), ``packed_scale``
  (11-10-11 within the chunk's log-scale box), ``packed_color`` (8-8-8-8: colour 0.5 + C0 f_dc within the
  chunk colour range, or within [0, 1] without one; alpha = opacity, read back as byte / 255);
* optional element ``sh``, uint8 ``f_rest_*`` (channel-major): q = clip(trunc(256 (f / 8 + 0.5)), 0, 255),
  read back at the bucket centre (q + 0.5) / 256 except 0 and 255, which read as the ends -4 and 4.

A unorm field of b bits stores t in [0, 1] as floor(t (2^b - 1) + 1/2): the decode error of a value inside
its chunk range is at most half a step, range / (2 (2^b - 1)). The writer orders splats along a Morton
(Z-order) curve first, as splat-transform does, so that each chunk's box is small.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.scene.ply import SH_C0, PlyError, PlyHeader, columns, read_elements

if TYPE_CHECKING:
    from scenesplat_stereo.scene.gaussians import GaussianScene

#: Splats per ``chunk`` row.
CHUNK_SIZE = 256
#: Log scales outside this range are clamped in the chunk boxes (splat-transform's clamp).
LOG_SCALE_CLAMP = 20.0
#: A chunk range narrower than this stores every value as its minimum (splat-transform's rule).
MIN_RANGE = 1e-5
#: Bits of the x, y, z fields of ``packed_position`` and ``packed_scale``.
XYZ_BITS = (11, 10, 11)
#: Bits of each of the three stored quaternion components.
ROTATION_BITS = 10
#: Range of the quantised higher SH coefficients (``sh`` element): [-SH_RANGE, SH_RANGE].
SH_RANGE = 4.0
#: Bits of the Morton code per axis, and the bucket size above which equal codes are sorted again.
MORTON_BITS, MORTON_REFINE = 10, 256

CHUNK_BOX = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"] + [
    f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"]
CHUNK_COLOUR = [f"{m}_{c}" for m in ("min", "max") for c in "rgb"]
PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
#: _OTHER_SLOTS[i]: the wxyz indices other than i, in order.
_OTHER_SLOTS = np.array([[j for j in range(4) if j != i] for i in range(4)])


# ---------------------------------------------------------------- reading

def _unorm(bits: np.ndarray, shift: int, width: int) -> np.ndarray:
    return ((bits >> np.uint32(shift)) & np.uint32((1 << width) - 1)).astype(np.float64) / ((1 << width) - 1)


def _unorm_111011(bits: np.ndarray) -> np.ndarray:
    """[N, 3] in [0, 1] from 11 (bits 21-31), 10 (bits 11-20) and 11 (bits 0-10) bit unsigned fields."""
    return np.stack([_unorm(bits, 21, 11), _unorm(bits, 11, 10), _unorm(bits, 0, 11)], 1)


def decode_compressed(header: PlyHeader) -> tuple[np.ndarray, ...]:
    """(means, quats wxyz, log scales, opacities, sh float32, finite rows) of a compressed file, float64."""
    path = header.path
    el = read_elements(header, {e.name for e in header.elements if e.name in ("chunk", "vertex", "sh")})
    chunk, vertex = el["chunk"], el["vertex"]
    n = len(vertex)
    if len(chunk) != -(-n // CHUNK_SIZE):
        raise PlyError(f"{path}: element 'chunk' has {len(chunk)} rows; {n} vertices need "
                       f"{-(-n // CHUNK_SIZE)} (one per {CHUNK_SIZE})")
    typed = [("vertex", p, 4) for p in PACKED]
    if "sh" in el:
        typed += [("sh", p, 1) for p in el["sh"].dtype.names or ()]
    for e, name, size in typed:
        t = (el[e].dtype.fields or {}).get(name, (None,))[0]
        if t is not None and (t.kind != "u" or t.itemsize != size):
            raise PlyError(f"{path}: element '{e}' property '{name}' must be {8 * size}-bit unsigned, "
                           f"got {t}")
    packed = columns(path, vertex, "vertex", PACKED).astype(np.uint32)
    colour_names = [c for c in CHUNK_COLOUR if c in (chunk.dtype.names or ())]
    if colour_names and len(colour_names) != len(CHUNK_COLOUR):
        raise PlyError(f"{path}: element 'chunk' has colour ranges {colour_names} but lacks "
                       f"{sorted(set(CHUNK_COLOUR) - set(colour_names))}")
    ranges = columns(path, chunk, "chunk", CHUNK_BOX + colour_names)[np.arange(n) // CHUNK_SIZE]
    pos, rot, scl, col = packed.T

    def lerp(t: np.ndarray, lo: int) -> np.ndarray:  # ranges[:, lo:lo+3] are the mins, +3 the maxes
        return ranges[:, lo:lo + 3] * (1.0 - t) + ranges[:, lo + 3:lo + 6] * t

    means, log_scales = lerp(_unorm_111011(pos), 0), lerp(_unorm_111011(scl), 6)
    rgba = np.stack([_unorm(col, s, 8) for s in (24, 16, 8, 0)], 1)
    colour = lerp(rgba[:, :3], 12) if colour_names else rgba[:, :3]
    # the largest component is recovered as sqrt(1 - sum of the others^2)
    others = np.stack([_unorm(rot, s, ROTATION_BITS) for s in (20, 10, 0)], 1) - 0.5
    others *= np.sqrt(2.0)
    largest = (rot >> np.uint32(30)).astype(np.int64)
    quats = np.empty((n, 4), dtype=np.float64)
    quats[np.arange(n)[:, None], _OTHER_SLOTS[largest]] = others
    quats[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - (others**2).sum(1)))
    k = (header.sh_degree + 1) ** 2
    sh = np.empty((n, k, 3), dtype=np.float32)
    sh[:, 0, :] = (colour - 0.5) / SH_C0
    if k > 1:
        if len(el["sh"]) != n:
            raise PlyError(f"{path}: element 'sh' has {len(el['sh'])} rows, element 'vertex' {n}")
        rest = columns(path, el["sh"], "sh", [f"f_rest_{i}" for i in range(3 * (k - 1))])
        t = np.where(rest == 0, 0.0, np.where(rest == 255, 1.0, (rest + 0.5) / 256.0))
        sh[:, 1:, :] = ((t - 0.5) * 2 * SH_RANGE).reshape(n, 3, k - 1).transpose(0, 2, 1)
    finite = np.isfinite(means).all(1) & np.isfinite(log_scales).all(1) & np.isfinite(sh).all((1, 2))
    return means, quats, log_scales, rgba[:, 3], sh, finite



# ---------------------------------------------------------------- writing

def _part1by2(v: np.ndarray) -> np.ndarray:
    """Spread the low 10 bits of v (uint32) to every third bit (bit i -> bit 3 i)."""
    v = v & np.uint32(0x3FF)
    v = (v ^ (v << np.uint32(16))) & np.uint32(0xFF0000FF)
    v = (v ^ (v << np.uint32(8))) & np.uint32(0x0300F00F)
    v = (v ^ (v << np.uint32(4))) & np.uint32(0x030C30C3)
    return (v ^ (v << np.uint32(2))) & np.uint32(0x09249249)


def morton_order(means: np.ndarray) -> np.ndarray:
    """Indices [N] that sort ``means`` [N, 3] along a Z-order curve (splat-transform's order).

    Each axis of the points' bounding box is cut into 2^10 cells, the 30-bit codes (z highest, then y,
    then x in each bit triple) are sorted stably, and every run of more than 256 equal codes is sorted
    again within its own box."""
    means = np.asarray(means, dtype=np.float64)
    order = np.arange(len(means))

    def refine(index: np.ndarray) -> np.ndarray:
        p = means[index]
        lo, hi = p.min(0), p.max(0)
        length = hi - lo
        if not np.isfinite(length).all() or not length.any():
            return index
        with np.errstate(divide="ignore"):
            mul = np.where(length == 0, 0.0, (1 << MORTON_BITS) / length)
        cell = np.minimum((1 << MORTON_BITS) - 1, (p - lo) * mul).astype(np.uint32)
        code = (_part1by2(cell[:, 2]) << np.uint32(2)) | (_part1by2(cell[:, 1]) << np.uint32(1)) \
            | _part1by2(cell[:, 0])
        by_code = np.argsort(code, kind="stable")
        index, code = index[by_code], code[by_code]
        starts = np.flatnonzero(np.r_[True, code[1:] != code[:-1]])
        ends = np.r_[starts[1:], len(code)]
        for s, e in zip(*(x[ends - starts > MORTON_REFINE] for x in (starts, ends))):
            index[s:e] = refine(index[s:e])
        return index

    return refine(order) if len(order) else order


def _blocks(values: np.ndarray) -> np.ndarray:
    """values [N, D] as float64 [C, CHUNK_SIZE, D], the last chunk padded with copies of the last row."""
    n, d = values.shape
    c = -(-n // CHUNK_SIZE)
    padded = np.empty((c * CHUNK_SIZE, d), dtype=np.float64)
    padded[:n] = values
    padded[n:] = values[-1] if n else 0.0
    return padded.reshape(c, CHUNK_SIZE, d)


def _unit_interval(blocks: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(v - lo) / (hi - lo) per chunk range (lo, hi [C, D]) of blocks [C, 256, D]: 0 at or below lo, 1 at or
    above hi, 0 where the range is narrower than MIN_RANGE. Returns [C * 256, D]."""
    lo, hi = lo[:, None, :].astype(np.float64), hi[:, None, :].astype(np.float64)
    span = hi - lo
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(span < MIN_RANGE, 0.0, (blocks - lo) / span)
    t = np.where(blocks <= lo, 0.0, np.where(blocks >= hi, 1.0, t))
    return t.reshape(-1, blocks.shape[2])


def _pack_unorm(t: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _pack_111011(t: np.ndarray) -> np.ndarray:
    x, y, z = (_pack_unorm(t[:, i], b) for i, b in enumerate(XYZ_BITS))
    return (x << np.uint32(21)) | (y << np.uint32(11)) | z


def _pack_rotation(quats: np.ndarray) -> np.ndarray:
    q = quats.astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    n = len(q)
    largest = np.abs(q).argmax(1)  # the first of equal magnitudes
    q *= np.where(q[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    others = q[np.arange(n)[:, None], _OTHER_SLOTS[largest]]
    codes = _pack_unorm(others * np.sqrt(0.5) + 0.5, ROTATION_BITS)
    return (largest.astype(np.uint32) << np.uint32(30)) | (codes[:, 0] << np.uint32(20)) \
        | (codes[:, 1] << np.uint32(10)) | codes[:, 2]


def save_compressed_ply(scene: GaussianScene, path: str | os.PathLike, durable: bool = True) -> Path:
    """Write ``scene`` in the compressed layout (module docstring), Morton-ordered, with colour ranges and,
    for SH degree > 0, the ``sh`` element. Atomic (``files.atomic_write_bytes``). Returns the path."""
    path = Path(path)
    n, k = len(scene), (scene.sh_degree + 1) ** 2
    order = morton_order(scene.means)
    log_scales = np.log(scene.scales[order].astype(np.float64)).astype(np.float32)  # the file's log scales
    colour = (scene.sh[order, 0, :].astype(np.float64) * SH_C0 + 0.5).astype(np.float32)
    blocks = [_blocks(scene.means[order]), _blocks(log_scales), _blocks(colour)]
    boxes = [(b.min(1), b.max(1)) for b in blocks]  # exact float32 values: the padding repeats a real row
    boxes[1] = tuple(np.clip(x, -LOG_SCALE_CLAMP, LOG_SCALE_CLAMP) for x in boxes[1])
    chunks = np.concatenate([part for box in boxes for part in box], axis=1).astype("<f4")
    position, scale, rgb = (_unit_interval(b, *box)[:n] for b, box in zip(blocks, boxes))
    vertex = np.empty((n, 4), dtype="<u4")
    vertex[:, 0] = _pack_111011(position)
    vertex[:, 1] = _pack_rotation(scene.quats[order])
    vertex[:, 2] = _pack_111011(scale)
    r, g, b = (_pack_unorm(rgb[:, i], 8) for i in range(3))
    alpha = _pack_unorm(scene.opacities[order].astype(np.float64), 8)
    vertex[:, 3] = (r << np.uint32(24)) | (g << np.uint32(16)) | (b << np.uint32(8)) | alpha
    lines = ["ply", "format binary_little_endian 1.0", f"element chunk {len(chunks)}"]
    lines += [f"property float {p}" for p in CHUNK_BOX + CHUNK_COLOUR]
    lines += [f"element vertex {n}"] + [f"property uint {p}" for p in PACKED]
    parts = [chunks, vertex]
    if k > 1:
        rest = scene.sh[order, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)).astype(np.float64)
        parts.append(np.clip(np.trunc((rest / (2 * SH_RANGE) + 0.5) * 256), 0, 255).astype(np.uint8))
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * (k - 1))]
    head = "\n".join(lines + ["end_header\n"]).encode("ascii")
    atomic_write_bytes(path, [head, *parts], durable=durable)
    return path
