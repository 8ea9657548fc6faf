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
from scenesplat_stereo.scene import row_tasks
from scenesplat_stereo.scene.ply import SH_C0, PlyError, PlyHeader, columns, read_elements

if TYPE_CHECKING:
    import torch

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
    """Spread the low 10 bits of v (int64) to every third bit (bit i -> bit 3 i)."""
    v = v & 0x3FF
    v = (v ^ (v << 16)) & 0xFF0000FF
    v = (v ^ (v << 8)) & 0x0300F00F
    v = (v ^ (v << 4)) & 0x030C30C3
    return (v ^ (v << 2)) & 0x09249249


#: ``_part1by2`` of every cell index, shifted for x, y and z: a code is three lookups and two ORs, not 43 bit
#: operations on the N cells (on 2 cores 3.3 against 13.6 ms at 202,752 Gaussians; on a GPU 5 kernels, not 43).
_SPREAD = np.stack([_part1by2(np.arange(1 << MORTON_BITS, dtype=np.int64)) << axis for axis in range(3)])


def _sorted(keys: torch.Tensor) -> torch.Tensor:
    """``keys`` (int64, distinct) in ascending order: torch's sort on a GPU, numpy's on the CPU (its SIMD sort: 3.5
    against 39 ms for 276,480 keys in one thread of the 2-core CPU machine)."""
    import torch

    return torch.sort(keys).values if keys.is_cuda else torch.from_numpy(np.sort(keys.numpy()))


def morton_order(means: np.ndarray, dev: torch.device | None = None) -> np.ndarray:
    """Indices [N] that sort ``means`` [N, 3] along a Z-order curve (splat-transform's order).

    Each axis of the points' bounding box is cut into 2^10 cells, the 30-bit codes (z highest, then y,
    then x in each bit triple) are sorted stably, and every run of more than 256 equal codes is sorted
    again within its own box. (The stable sort is a plain sort of the 64-bit keys code << 32 | position.)
    In torch on ``dev`` (default ``row_tasks.device()``; the sort in numpy on the CPU, ``_sorted``): on a GPU the
    sort of 202,752 keys takes well under a millisecond, where numpy's keys and sort took 24 ms of a 16-core host
    beside the writers' other threads; every step is exact (float64 differences and products, integer bit
    operations), so the order is the same on any device."""
    import torch  # only for writing: the reader does without it

    dev = dev or row_tasks.device()
    columns = torch.from_numpy(np.ascontiguousarray(means)).to(dev).double().T.contiguous()  # [3, N]
    spread = torch.from_numpy(_SPREAD).to(dev)

    def refine(index: torch.Tensor) -> torch.Tensor:
        p = columns if len(index) == columns.shape[1] else columns[:, index]
        lo, hi = p.amin(1), p.amax(1)
        length = hi - lo
        if not bool(torch.isfinite(length).all() and length.any()):
            return index
        mul = torch.where(length == 0, 0.0, (1 << MORTON_BITS) / length)
        cell = ((p - lo[:, None]) * mul[:, None]).clamp_(max=(1 << MORTON_BITS) - 1).long()  # >= 0: the floor
        code = spread[2][cell[2]] | spread[1][cell[1]] | spread[0][cell[0]]
        keys = _sorted((code << 32) | torch.arange(len(index), device=dev))
        index, code = index[keys & 0xFFFFFFFF], keys >> 32
        starts = torch.nonzero(torch.cat([code[:1] == code[:1], code[1:] != code[:-1]])).squeeze(1)
        ends = torch.cat([starts[1:], starts.new_tensor([len(code)])])
        long = ends - starts > MORTON_REFINE
        for s, e in zip(starts[long].tolist(), ends[long].tolist()):
            index[s:e] = refine(index[s:e])
        return index

    n = columns.shape[1]
    return refine(torch.arange(n, device=dev)).cpu().numpy() if n else np.arange(0)


def _unit_interval(columns: np.ndarray, box: np.ndarray, clamp: float | None = None) -> np.ndarray:
    """``columns`` [3, C * 256] (float32, one row per axis; whole chunks, the last padded with copies of its
    last value) -> t [3, C * 256] float64 in [0, 1] within each chunk's box, whose min and max per axis
    (clamped to [-clamp, clamp]) go to ``box`` [C, 6] (mins, then maxes).

    t = (v - lo) / (hi - lo), 0 at or below lo, 1 at or above hi, and in a range narrower than MIN_RANGE 0
    but at its hi (above lo), as splat-transform does."""
    blocks = columns.reshape(3, -1, CHUNK_SIZE)
    lo, hi = blocks.min(2), blocks.max(2)  # exact float32 values: the padding repeats a real value
    _signed_zero_bounds(blocks, lo, hi)
    if clamp is not None:
        np.clip(lo, -clamp, clamp, out=lo)
        np.clip(hi, -clamp, clamp, out=hi)
    box[:, :3], box[:, 3:] = lo.T, hi.T
    lo64, hi64 = lo[:, :, None].astype(np.float64), hi[:, :, None].astype(np.float64)
    span = hi64 - lo64
    t = np.subtract(blocks, lo64, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t /= span
    np.clip(t, 0.0, 1.0, out=t)  # v <= lo gives t <= 0 and v >= hi t >= 1: rounding is monotone
    narrow = span < MIN_RANGE
    if narrow.any():
        np.copyto(t, (blocks > lo64) & (blocks >= hi64), where=np.broadcast_to(narrow, t.shape))
    return t.reshape(3, -1)


def _signed_zero_bounds(blocks: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """Give bounds at zero the sign JavaScript's Math.min and Math.max give them (splat-transform's chunk
    boxes): a lower bound -0 when some value of its block is -0, else +0; an upper bound +0 when some value is
    +0, else -0. numpy's min and max return either zero. In place; only blocks with a bound at zero are read."""
    for bound, negative in ((lo, True), (hi, False)):
        at_zero = np.nonzero(bound == 0)
        if len(at_zero[0]):
            values = blocks[at_zero]  # [z, CHUNK_SIZE]: the blocks whose bound is a zero
            signed = ((values == 0) & (np.signbit(values) == negative)).any(1)
            bound[at_zero] = np.where(signed == negative, -0.0, 0.0)


def _to_unorm(t: np.ndarray, bits: int) -> np.ndarray:
    """t in [0, 1] (float64, scaled in place) -> uint32 floor(t (2^bits - 1) + 1/2)."""
    t *= (1 << bits) - 1
    t += 0.5
    return t.astype(np.uint32)  # floor of t >= 0


def _pack_111011(t: np.ndarray, m: int) -> np.ndarray:
    """t [3, >= m] in [0, 1] -> the first m 11-10-11 words (x in bits 21-31, y 11-20, z 0-10)."""
    x, y, z = (_to_unorm(t[i, :m], b) for i, b in enumerate(XYZ_BITS))
    return (x << np.uint32(21)) | (y << np.uint32(11)) | z


def largest_component(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index uint8 [m], value [m]) of each column's largest |component| of q [4, m], the first of equals (as
    ``np.argmax``): a tournament of the pairs (0, 1) and (2, 3), several times faster than argmax along rows of
    4 or masked updates."""
    a = np.abs(q)
    first, second = (a[1] > a[0]).view(np.uint8), (a[3] > a[2]).view(np.uint8) + np.uint8(2)
    index = np.where(np.maximum(a[2], a[3]) > np.maximum(a[0], a[1]), second, first)
    return index, q[index, np.arange(q.shape[1])]


def _pack_rotation(q: np.ndarray) -> np.ndarray:
    """wxyz quaternions as columns q [4, m] (float64, normalised and changed in place) -> uint32 [m]: the index
    of the largest |component| (the first of equals) in bits 30-31, then the three others in wxyz order as
    10-bit unorm(c / sqrt(2) + 1/2), the quaternion negated first where the largest is negative."""
    q /= np.linalg.norm(q, axis=0)  # ((w^2 + x^2) + y^2) + z^2, as numpy's row norm of the [m, 4] rows
    largest, value = largest_component(q)
    q *= np.where(value < 0, -1.0, 1.0)
    word = largest.astype(np.uint32) << np.uint32(30)
    for j, shift in enumerate((20, 10, 0)):  # the j-th component other than the largest
        c = np.where(largest <= j, q[j + 1], q[j])
        c *= np.sqrt(0.5)
        c += 0.5
        np.clip(c, 0.0, 1.0, out=c)
        word |= _to_unorm(c, ROTATION_BITS) << np.uint32(shift)
    return word


def _columns(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Rows ``index`` of a contiguous [N, D] as contiguous columns [D, len(index)] (np.take then a transposed
    copy: several times faster than taking along the columns of a transposed view; np.take copies a
    non-contiguous input whole first, so strided views are indexed instead)."""
    return np.ascontiguousarray(np.take(a, index, axis=0).T)


def _fill_rows(scene: GaussianScene, index: np.ndarray, chunks: np.ndarray, vertex: np.ndarray,
               rest: np.ndarray) -> None:
    """The file's rows ``index`` of the scene (whole chunks, the last one may be short): their chunk table
    rows ``chunks`` [c, 18], packed vertices ``vertex`` [m, 4] and higher SH bytes ``rest`` [m, 3 (K-1)]
    (the module docstring's layout). Works on columns (one row per axis) gathered through the index padded
    to whole chunks with its last row, as the format pads the last chunk's box."""
    m = len(index)
    padded = np.empty(-(-m // CHUNK_SIZE) * CHUNK_SIZE, np.intp)
    padded[:m], padded[m:] = index, index[-1]
    means = _columns(scene.means, padded)
    log_scales = np.log(_columns(scene.scales, padded), dtype=np.float64).astype(np.float32)
    colour = np.multiply(scene.sh[padded, 0, :].T, SH_C0, dtype=np.float64)
    colour += 0.5
    vertex[:, 0] = _pack_111011(_unit_interval(means, chunks[:, 0:6]), m)
    vertex[:, 1] = _pack_rotation(_columns(scene.quats, index).astype(np.float64))
    vertex[:, 2] = _pack_111011(_unit_interval(log_scales, chunks[:, 6:12], LOG_SCALE_CLAMP), m)
    rgb = _unit_interval(colour.astype(np.float32, order="C"), chunks[:, 12:18])  # C: rows reduce fast
    r, g, b = (_to_unorm(rgb[i, :m], 8) for i in range(3))
    alpha = _to_unorm(np.take(scene.opacities, index).astype(np.float64), 8)
    vertex[:, 3] = (r << np.uint32(24)) | (g << np.uint32(16)) | (b << np.uint32(8)) | alpha
    if rest.shape[1]:
        # q = clip(trunc(256 (f / 8 + 1/2)), 0, 255) = the float64 32 f + 128 (the same rounding), clipped
        k1 = rest.shape[1] // 3
        u = np.empty((m, 3, k1), np.float64)
        np.multiply(scene.sh[index, 1:, :].transpose(0, 2, 1), 256.0 / (2 * SH_RANGE), out=u)
        u += 128.0
        np.clip(u, 0.0, 255.0, out=u)
        np.copyto(rest.reshape(m, 3, k1), u, casting="unsafe")  # truncation


def save_compressed_ply(scene: GaussianScene, path: str | os.PathLike, durable: bool = True) -> Path:
    """Write ``scene`` in the compressed layout (module docstring), Morton-ordered, with colour ranges and,
    for SH degree > 0, the ``sh`` element. Atomic (``files.atomic_write_bytes``). Returns the path.

    After the Morton sort the rows are packed in slices of whole chunks on the shared pool (``row_tasks``),
    each slice writing its own rows of the tables; the bytes do not depend on the split."""
    path = Path(path)
    n, k = len(scene), (scene.sh_degree + 1) ** 2
    order = morton_order(scene.means)
    chunks = np.empty((-(-n // CHUNK_SIZE), len(CHUNK_BOX + CHUNK_COLOUR)), "<f4")
    vertex = np.empty((n, len(PACKED)), "<u4")
    rest = np.empty((n, 3 * (k - 1)), np.uint8)

    def fill(a: int, b: int) -> None:  # a is a multiple of CHUNK_SIZE
        _fill_rows(scene, order[a:b], chunks[a // CHUNK_SIZE:-(-b // CHUNK_SIZE)], vertex[a:b], rest[a:b])

    row_tasks.wait_all(row_tasks.submit_rows(fill, n))
    lines = ["ply", "format binary_little_endian 1.0", f"element chunk {len(chunks)}"]
    lines += [f"property float {p}" for p in CHUNK_BOX + CHUNK_COLOUR]
    lines += [f"element vertex {n}"] + [f"property uint {p}" for p in PACKED]
    parts = [chunks, vertex]
    if k > 1:
        parts.append(rest)
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * (k - 1))]
    head = "\n".join(lines + ["end_header\n"]).encode("ascii")
    atomic_write_bytes(path, [head, *parts], durable=durable)
    return path
