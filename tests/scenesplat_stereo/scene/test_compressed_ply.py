"""The PlayCanvas compressed .ply writer (scenesplat_stereo.scene.compressed_ply): round trip through our reader
within each field's quantisation (bounds from the bit widths over the chunk ranges read from the file by
hand), the Morton order against a bit-by-bit version written here, and extreme inputs. (The reader is held
against the format description in tests/scenesplat_stereo/scene/test_gaussians_compressed.py; tests/scenesplat_stereo/scene/test_scene_files.py checks the
writer against splat-transform's.)"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.scene.compressed_ply import morton_order, save_compressed_ply
from scenesplat_stereo.scene.gaussians import GaussianScene, load_ply
from scenesplat_stereo.scene.ply import SH_C0
from tests.support.ply_helpers import EPS32, random_scene


def file_tables(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The chunk table [C,18] float64 and the packed vertices [N,4] uint32, read by hand."""
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    text = head.decode()
    c, n = (int(re.search(rf"element {e} (\d+)", text).group(1)) for e in ("chunk", "vertex"))
    assert re.findall(r"property float (\w+)", text) == [
        "min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y", "min_scale_z",
        "max_scale_x", "max_scale_y", "max_scale_z", "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
    chunks = np.frombuffer(body, "<f4", c * 18).reshape(c, 18).astype(np.float64)
    return chunks, np.frombuffer(body, "<u4", n * 4, c * 72).reshape(n, 4)


@pytest.mark.parametrize("degree,n", [(0, 1000), (1, 300), (2, 513), (3, 256)])
def test_round_trip_within_the_quantisation(tmp_path: Path, degree: int, n: int) -> None:
    rng = np.random.default_rng(degree)
    scene = random_scene(rng, n, degree)
    scene.sh[:, 1:] = rng.uniform(-4, 3.99, scene.sh[:, 1:].shape)
    path = save_compressed_ply(scene, tmp_path / "s.compressed.ply")
    back = load_ply(path, strict=True)
    ref = scene.subset(morton_order(scene.means))  # the file's order
    chunks, _ = file_tables(path)
    assert len(back) == n and back.sh_degree == degree and len(chunks) == math.ceil(n / 256)
    ci = np.arange(n) // 256
    lo, hi = chunks[ci, 0:3], chunks[ci, 3:6]
    # the chunk boxes are those of the Gaussians they hold
    for c in range(len(chunks)):
        m = ref.means[c * 256:(c + 1) * 256].astype(np.float64)
        np.testing.assert_array_equal(chunks[c, 0:6], np.r_[m.min(0), m.max(0)])
    half = (hi - lo) / (2 * (2.0 ** np.array([11, 10, 11]) - 1))
    assert (np.abs(back.means - ref.means) <= half + 2 * EPS32 * np.abs(ref.means)).all()
    log_lo, log_hi = chunks[ci, 6:9], chunks[ci, 9:12]
    half_log = (log_hi - log_lo) / (2 * (2.0 ** np.array([11, 10, 11]) - 1))
    log_err = np.abs(np.log(back.scales.astype(np.float64)) - np.log(ref.scales.astype(np.float64)))
    assert (log_err <= half_log + 4 * EPS32 * 20).all()
    half_dc = (chunks[ci, 15:18] - chunks[ci, 12:15]) / (2 * 255) / SH_C0
    assert (np.abs(back.sh[:, 0] - ref.sh[:, 0]) <= half_dc + 8 * EPS32 * (1 + np.abs(ref.sh[:, 0]))).all()
    assert (np.abs(back.opacities - ref.opacities) <= 0.5 / 255 + EPS32).all()
    h = math.sqrt(2) / (2 * 1023)  # see tests/scenesplat_stereo/scene/test_gaussians_compressed.py for the rotation bound
    dist = np.minimum(np.linalg.norm(back.quats - ref.quats, axis=1), np.linalg.norm(back.quats + ref.quats, axis=1))
    assert (dist <= 2 * math.sqrt(12) * h).all()
    if degree:  # 256 buckets of width 1/32 over [-4, 4): the centre is within 1/64, the two end codes 1/32
        assert (np.abs(back.sh[:, 1:] - ref.sh[:, 1:]) <= 1 / 32 + EPS32).all()
        inner = np.abs(ref.sh[:, 1:]) < 4 - 1 / 32
        assert (np.abs(back.sh[:, 1:] - ref.sh[:, 1:])[inner] <= 1 / 64 + EPS32).all()


def test_extremes_flat_chunks_clamped_scales_and_sh(tmp_path: Path) -> None:
    """A chunk whose values are all equal stores its minimum (range < 1e-5); log scales beyond +-20 clamp;
    SH beyond +-4 clamps to the ends; opacity 0 and 1 are exact."""
    n = 10
    q = np.tile([[0.0, 0.0, 0.0, -1.0]], (n, 1)).astype(np.float32)  # largest component negative: flipped
    scene = GaussianScene(np.full((n, 3), 1.5, np.float32), q, np.full((n, 3), 1e-12, np.float32),
                          np.linspace(0, 1, n).astype(np.float32), np.full((n, 4, 3), 9.0, np.float32), 1)
    back = load_ply(save_compressed_ply(scene, tmp_path / "x.compressed.ply"))
    np.testing.assert_allclose(back.means, 1.5, rtol=1e-7)
    np.testing.assert_allclose(np.log(back.scales), -20.0, rtol=1e-6)  # ln 1e-12 = -27.6 clamped
    np.testing.assert_allclose(back.quats[:, 3], 1.0, atol=1e-6)  # -q, the same rotation; 0 stores as 6.9e-4
    assert back.opacities[0] == 0 and back.opacities[-1] == 1
    np.testing.assert_allclose(back.sh[:, 1:], 4.0)


def test_empty_scene(tmp_path: Path) -> None:
    back = load_ply(save_compressed_ply(random_scene(np.random.default_rng(0), 0, 2), tmp_path / "e.compressed.ply"))
    assert len(back) == 0 and back.sh_degree == 2


def _spread(v: int) -> int:
    """Bit i of v (10 bits) -> bit 3 i."""
    return sum(((v >> i) & 1) << (3 * i) for i in range(10))


def reference_morton(means: np.ndarray) -> list[int]:
    """Z-order: 2^10 cells per axis of the box, code = z y x bit triples, stable; runs of > 256 equal codes
    sorted again in their own box (splat-transform's rule), one point at a time."""
    def order(index: list[int]) -> list[int]:
        p = means[index].astype(np.float64)
        lo, hi = p.min(0), p.max(0)
        if not (hi - lo).any():
            return index
        mul = [0.0 if hi[a] == lo[a] else 1024 / (hi[a] - lo[a]) for a in range(3)]
        codes = []
        for row in p:
            cell = [int(min(1023, (row[a] - lo[a]) * mul[a])) for a in range(3)]
            codes.append((_spread(cell[2]) << 2) | (_spread(cell[1]) << 1) | _spread(cell[0]))
        ranked = sorted(range(len(index)), key=lambda i: codes[i])  # Python's sort is stable
        index, codes = [index[i] for i in ranked], [codes[i] for i in ranked]
        out, start = [], 0
        while start < len(index):
            end = start
            while end < len(index) and codes[end] == codes[start]:
                end += 1
            run = index[start:end]
            out += order(run) if end - start > 256 else run
            start = end
        return out
    return order(list(range(len(means))))


def test_morton_order_matches_a_bit_by_bit_version() -> None:
    rng = np.random.default_rng(5)
    means = rng.normal(0, 1, (2000, 3)).astype(np.float32)
    means[:600] = rng.normal(0, 1e-4, (600, 3))  # a dense clump: one cell of the outer box, refined
    means[600:700] = [0.5, 0.5, 0.5]  # identical points keep their order
    means[700:800, 2] = 0.25  # a flat slab
    np.testing.assert_array_equal(morton_order(means), reference_morton(means))


def _unorm(t: float, bits: int) -> int:
    top = (1 << bits) - 1
    return int(min(top, max(0, math.floor(t * top + 0.5))))


def js_min(values: list[float]) -> float:
    """JavaScript's Math.min (splat-transform's): -0 below +0."""
    return min(values, key=lambda v: (v, math.copysign(1.0, v)))


def js_max(values: list[float]) -> float:
    """JavaScript's Math.max: +0 above -0."""
    return max(values, key=lambda v: (v, math.copysign(1.0, v)))


def reference_file(scene: GaussianScene) -> bytes:
    """The compressed layout from its description (module docstring of scenesplat_stereo.scene.compressed_ply, as
    splat-transform writes it), chunk by chunk and value by value in Python floats, in ``reference_morton``'s
    order: boxes of the float32 values by Math.min and Math.max (the last chunk padded with its last row; log
    scales clamped to +-20 in the box), t = (v - lo) / (hi - lo) (0 at or below lo, 1 at or above hi, 0 in a range under 1e-5),
    unorm fields floor(t (2^b - 1) + 1/2), SH trunc(256 (f / 8 + 1/2)) clamped, channel-major."""
    n, k = len(scene), (scene.sh_degree + 1) ** 2
    order = reference_morton(scene.means)
    f32 = lambda x: float(np.float32(x))  # noqa: E731
    fields = {"position": [[float(v) for v in scene.means[i]] for i in order],
              "scale": [[f32(math.log(float(s))) for s in scene.scales[i]] for i in order],
              "colour": [[f32(float(c) * SH_C0 + 0.5) for c in scene.sh[i, 0]] for i in order]}
    chunks, vertex = [], []
    for start in range(0, n, 256):
        rows = list(range(start, min(start + 256, n)))
        padded = rows + [n - 1] * (256 - len(rows))
        t, box = {}, []
        for name, values in fields.items():
            lo = [js_min([values[r][a] for r in padded]) for a in range(3)]
            hi = [js_max([values[r][a] for r in padded]) for a in range(3)]
            if name == "scale":
                lo, hi = ([min(20.0, max(-20.0, v)) for v in x] for x in (lo, hi))
            box += [(lo, hi)]

            def unit(v: float, a: int, lo=lo, hi=hi) -> float:
                if v <= lo[a]:
                    return 0.0
                if v >= hi[a]:
                    return 1.0
                return 0.0 if hi[a] - lo[a] < 1e-5 else (v - lo[a]) / (hi[a] - lo[a])
            t[name] = [[unit(values[r][a], a) for a in range(3)] for r in rows]
        chunks.append([v for lo, hi in box for v in lo + hi])
        for j, r in enumerate(rows):
            pos, scl, col = (t[name][j] for name in ("position", "scale", "colour"))
            q = [float(v) for v in scene.quats[order[r]]]
            norm = math.sqrt(sum(v * v for v in q))
            q = [v / norm for v in q]
            big = max(range(4), key=lambda i: (abs(q[i]), -i))  # the first of equal magnitudes
            q = [-v for v in q] if q[big] < 0 else q
            codes = [_unorm(q[i] * math.sqrt(0.5) + 0.5, 10) for i in range(4) if i != big]
            vertex.append([
                _unorm(pos[0], 11) << 21 | _unorm(pos[1], 10) << 11 | _unorm(pos[2], 11),
                big << 30 | codes[0] << 20 | codes[1] << 10 | codes[2],
                _unorm(scl[0], 11) << 21 | _unorm(scl[1], 10) << 11 | _unorm(scl[2], 11),
                _unorm(col[0], 8) << 24 | _unorm(col[1], 8) << 16 | _unorm(col[2], 8) << 8
                | _unorm(float(scene.opacities[order[r]]), 8)])
    sh = [[int(min(255, max(0, math.trunc((float(scene.sh[i, j, c]) / 8 + 0.5) * 256))))
           for c in range(3) for j in range(1, k)] for i in order]
    lines = ["ply", "format binary_little_endian 1.0", f"element chunk {len(chunks)}"]
    lines += [f"property float {m}_{a}" for m in ("min", "max") for a in "xyz"]
    lines += [f"property float {m}_scale_{a}" for m in ("min", "max") for a in "xyz"]
    lines += [f"property float {m}_{c}" for m in ("min", "max") for c in "rgb"]
    lines += [f"element vertex {n}"] + [f"property uint packed_{p}" for p in ("position", "rotation", "scale",
                                                                              "color")]
    body = np.array(chunks, "<f4").tobytes() + np.array(vertex, "<u4").tobytes()
    if k > 1:
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * (k - 1))]
        body += np.array(sh, np.uint8).tobytes()
    return "\n".join(lines + ["end_header\n"]).encode() + body


@pytest.mark.parametrize("degree,n", [(0, 2600), (2, 2400)])
def test_writer_bytes_equal_the_layout_point_by_point(tmp_path: Path, degree: int, n: int) -> None:
    """Rows split over many slices (``row_tasks``), clumps, flat, narrow and clamped chunks, chunk bounds at -0
    and +0, equal quaternion components, SH beyond the ends and at rounding ties: the bytes of the layout's
    description."""
    from scenesplat_stereo.scene import row_tasks

    rng = np.random.default_rng(20 + degree)
    scene = random_scene(rng, n, degree)
    scene.means[:300] = rng.normal(0, 1e-4, (300, 3))  # a clump: refined Morton runs
    scene.means[300:812] = [0.5, -0.5, 2.0]  # flat chunks (range 0): 512 points hold a whole chunk
    scene.means[812:1324] = [0.3, -0.2, 0.25]
    scene.means[812:1324, 2] += rng.integers(0, 4, 512) * 2.0**-25  # narrow ones (0 < range < 1e-5)
    scene.scales[:200] = np.exp(rng.choice([-25.0, 22.0], (200, 3)))  # log scales beyond +-20
    scene.quats[900:1200] = rng.choice([-0.5, 0.5], (300, 4))
    # a cluster with x >= 0 and y <= 0 and zeros there: chunk bounds at zero, in chunks with both zeros (of
    # even index in the file, where the zero's sign does not move a point) and with one
    scene.means[1324:2348] = rng.uniform(0, 1, (1024, 3)) * [1, -1, 1] + [0, 0, 12]
    rows = rng.integers(1324, 2348, (2, 200))
    scene.means[rows[0], 0], scene.means[rows[1], 1] = 0.0, -0.0
    chunk = np.argsort(morton_order(scene.means)) // 256
    for axis in (0, 1):
        flip = rows[axis][(chunk[rows[axis]] % 2 == 0) & (rng.uniform(size=200) < 0.5)]
        scene.means[flip, axis] *= -1
    scene.sh[:, 1:] = rng.uniform(-4.5, 4.5, scene.sh[:, 1:].shape)
    ties = [-4.0, 4.0, 0.0, -0.0, -2.0**-52, -2.0**-53, 1 / 32, -1 / 32]  # 32 f + 128 rounds to 128 at -2^-53
    scene.sh[:100, 1:] = rng.choice(ties, scene.sh[:100, 1:].shape)
    original = row_tasks.ROWS_PER_TASK
    try:
        row_tasks.ROWS_PER_TASK = 512
        data = save_compressed_ply(scene, tmp_path / "s.compressed.ply").read_bytes()
    finally:
        row_tasks.ROWS_PER_TASK = original
    assert data == reference_file(scene)
