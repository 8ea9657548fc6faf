"""scenesplat_stereo.scene.spz against files packed here from the format description (nianticlabs/spz README and
load-spz.cc), decoded point by point in float64; the writer's round trip within each field's quantisation
step; every malformed file. (tests/scenesplat_stereo/scene/test_scene_files.py checks both against Niantic's own encoder.)"""

from __future__ import annotations

import ctypes
import ctypes.util
import gzip
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.scene.gaussians import GaussianScene
from scenesplat_stereo.scene.scene_files import scene_info
from scenesplat_stereo.scene.spz import SpzError, encode_spz, load_spz, save_spz
from tests.support.paths import SPLAT_TRANSFORM
from tests.support.ply_helpers import EPS32, random_scene

MAGIC = 0x5053474E


def pack_file(path: Path, version: int, degree: int, fbits: int, fields: dict, gzip_it: bool = True) -> Path:
    """A .spz from raw byte fields (positions int [N,3] (version 1: float16 [N, 3]), alphas, colours [N,3],
    scales [N,3], rotation bytes [N,3|4], sh bytes [N,(K-1)*3]); the header as the README states it."""
    n = len(fields["alphas"])
    header = np.array([MAGIC, version, n], "<u4").tobytes() + bytes([degree, fbits, 0, 0])
    if version == 1:
        pos_bytes = np.asarray(fields["positions"], "<f2").view(np.uint8)
    else:
        pos = np.asarray(fields["positions"], dtype=np.int64) & 0xFFFFFF
        pos_bytes = np.stack([(pos >> s) & 0xFF for s in (0, 8, 16)], -1).astype(np.uint8)  # [N,3,3] little-endian
    body = b"".join(np.ascontiguousarray(x, dtype=np.uint8).tobytes() for x in (
        pos_bytes, fields["alphas"], fields["colours"], fields["scales"], fields["rotations"], fields["sh"]))
    data = header + body
    path.write_bytes(gzip.compress(data) if gzip_it else data)
    return path


def reference_decode(version: int, degree: int, fbits: int, f: dict) -> dict:
    """The format description, one point at a time, float64."""
    k = (degree + 1) ** 2
    out = {key: [] for key in ("means", "quats", "scales", "opacities", "sh")}
    for i in range(len(f["alphas"])):
        out["means"].append([float(v) if version == 1 else int(v) / 2**fbits for v in f["positions"][i]])
        out["scales"].append([math.exp(int(s) / 16 - 10) for s in f["scales"][i]])
        out["opacities"].append(int(f["alphas"][i]) / 255)
        r = [int(b) for b in f["rotations"][i]]
        if version < 3:
            xyz = [b / 127.5 - 1 for b in r]
            w = math.sqrt(max(0.0, 1 - sum(v * v for v in xyz)))
            q = [w, *xyz]
        else:
            comp = r[0] | r[1] << 8 | r[2] << 16 | r[3] << 24
            largest = comp >> 30
            xyzw = [0.0] * 4
            for j in (3, 2, 1, 0):
                if j == largest:
                    continue
                mag, neg = comp & 511, (comp >> 9) & 1
                comp >>= 10
                xyzw[j] = (-1 if neg else 1) * math.sqrt(0.5) * mag / 511
            xyzw[largest] = math.sqrt(max(0.0, 1 - sum(v * v for v in xyzw)))
            q = [xyzw[3], *xyzw[:3]]
        norm = math.sqrt(sum(v * v for v in q))
        out["quats"].append([v / norm for v in q])
        coeffs = np.zeros((k, 3))
        coeffs[0] = [(int(c) / 255 - 0.5) / 0.15 for c in f["colours"][i]]
        for j in range(1, k):
            for c in range(3):  # coefficient-major, colour fastest
                coeffs[j, c] = (int(f["sh"][i][(j - 1) * 3 + c]) - 128) / 128
        out["sh"].append(coeffs)
    return {key: np.array(v, dtype=np.float64) for key, v in out.items()}


def random_fields(rng: np.random.Generator, n: int, version: int, degree: int) -> dict:
    k = (degree + 1) ** 2
    byte = lambda *shape: rng.integers(0, 256, shape).astype(np.uint8)  # noqa: E731
    rot = byte(n, 4 if version == 3 else 3)
    if version < 3:  # keep |xyz| <= 1 mostly, as a writer would
        rot = (np.clip(rng.normal(0, 0.4, (n, 3)), -1, 1) * 127.5 + 127.5).astype(np.uint8)
    positions = rng.normal(0, 50, (n, 3)).astype(np.float16) if version == 1 else \
        rng.integers(-(1 << 23), 1 << 23, (n, 3))
    return {"positions": positions, "alphas": byte(n), "colours": byte(n, 3),
            "scales": byte(n, 3), "rotations": rot, "sh": byte(n, 3 * (k - 1))}


@pytest.mark.parametrize("version,degree", [(3, 0), (3, 1), (3, 2), (3, 3), (2, 1), (1, 0), (1, 2)])
def test_reader_matches_the_format_description(tmp_path: Path, version: int, degree: int) -> None:
    rng = np.random.default_rng(10 * version + degree)
    fields = random_fields(rng, 200, version, degree)
    if version > 1:
        fields["positions"][:3] = [[-(1 << 23), 0, (1 << 23) - 1], [-1, 1, 0], [5, -5, 1 << 22]]  # sign extension
    path = pack_file(tmp_path / "r.spz", version, degree, 10, fields)
    scene, ref = load_spz(path), reference_decode(version, degree, 10, fields)
    assert scene.sh_degree == degree and len(scene) == 200 and scene_info(path) == (200, degree)
    np.testing.assert_array_equal(scene.means, ref["means"].astype(np.float32))  # exact in float32
    np.testing.assert_allclose(scene.scales, ref["scales"], rtol=2 * EPS32)
    np.testing.assert_allclose(scene.opacities, ref["opacities"], atol=EPS32)
    np.testing.assert_allclose(scene.sh, ref["sh"], atol=4 * EPS32 * np.abs(ref["sh"]).max())
    np.testing.assert_allclose(scene.quats, ref["quats"], atol=4 * EPS32)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_within_the_quantisation_step(tmp_path: Path, degree: int) -> None:
    rng = np.random.default_rng(degree)
    n = 500
    base = random_scene(rng, n, degree)
    k = (degree + 1) ** 2
    sh = np.concatenate([rng.uniform(-3.3, 3.3, (n, 1, 3)), rng.uniform(-1, 0.96, (n, k - 1, 3))], 1)
    scene = GaussianScene(base.means, base.quats, np.exp(rng.uniform(-9.9, 5.9, (n, 3))).astype(np.float32),
                          base.opacities, sh.astype(np.float32), degree)
    back = load_spz(save_spz(scene, tmp_path / "s.spz"))
    assert back.sh_degree == degree and len(back) == n
    step = 2.0 ** -12  # 12 fractional bits for |x| < 2048 m
    assert (np.abs(back.means - scene.means) <= step / 2).all()
    log_err = np.abs(np.log(back.scales.astype(np.float64)) - np.log(scene.scales.astype(np.float64)))
    assert (log_err <= 1 / 32 + 4 * EPS32 * 10).all()
    assert (np.abs(back.opacities - scene.opacities) <= 0.5 / 255 + EPS32).all()
    assert (np.abs(back.sh[:, 0] - scene.sh[:, 0]) <= 0.5 / (0.15 * 255) + 8 * EPS32).all()
    if degree:
        assert (np.abs(back.sh[:, 1:4] - scene.sh[:, 1:4]) <= 4.5 / 128 + EPS32).all()
        assert (np.abs(back.sh[:, 4:] - scene.sh[:, 4:]) <= 8.5 / 128 + EPS32).all()
    # Each of the three stored components is off by <= h = sqrt(1/2) / (2 * 511), the largest m >= 1/2 by
    # <= 3h, and normalising at most doubles the distance (as for the compressed .ply's 10-bit codes).
    h = math.sqrt(0.5) / (2 * 511)
    dist = np.minimum(np.linalg.norm(back.quats - scene.quats, axis=1),
                      np.linalg.norm(back.quats + scene.quats, axis=1))
    assert (dist <= 2 * math.sqrt(12) * h).all()


def test_large_scenes_use_fewer_fractional_bits_and_huge_ones_are_refused(tmp_path: Path) -> None:
    scene = random_scene(np.random.default_rng(1), 20, 0)
    scene.means[0] = [3000.0, -5000.0, 1.0]  # beyond 2^23 / 2^12 = 2048 m
    data = encode_spz(scene)
    bits = data[13]
    assert bits == 10  # 5000 * 2^10 < 2^23 <= 5000 * 2^11
    back = load_spz(save_spz(scene, tmp_path / "big.spz"))
    assert np.abs(back.means - scene.means).max() <= 2.0 ** -(bits + 1)
    scene.means[0, 0] = 2.0**24
    with pytest.raises(SpzError, match="do not fit 24-bit fixed point"):
        save_spz(scene, tmp_path / "huge.spz")
    assert not (tmp_path / "huge.spz").exists()


def test_empty_scene_round_trips(tmp_path: Path) -> None:
    scene = random_scene(np.random.default_rng(0), 0, 2)
    back = load_spz(save_spz(scene, tmp_path / "e.spz"))
    assert len(back) == 0 and back.sh_degree == 2


@pytest.mark.parametrize("case,message", [
    ("not gzip", "not a .spz file"),
    ("version 4", "header numPoints 0, shDegree 0: need >= 1 point"),
    ("corrupt gzip", "corrupt gzip stream"),
    ("short header", "header truncated"),
    ("magic", "header magic is 0x12345678"),
    ("version 7", "header version 7 is not supported"),
    ("degree 4", "header shDegree 4"),
    ("truncated body", "body truncated: header numPoints 10 needs"),
    ("version 1 inf", "positions: 1 float16 positions are inf or NaN"),
])
def test_bad_files(tmp_path: Path, case: str, message: str) -> None:
    fields = random_fields(np.random.default_rng(2), 10, 3, 1)
    path = pack_file(tmp_path / "bad.spz", 3, 1, 12, fields)
    raw = gzip.decompress(path.read_bytes())
    edits = {"not gzip": lambda: b"hello world",
             "version 4": lambda: b"NGSP" + np.array([4], "<u4").tobytes() + bytes(24),
             "corrupt gzip": lambda: path.read_bytes()[:30],
             "short header": lambda: gzip.compress(raw[:10]),
             "magic": lambda: gzip.compress(np.array([0x12345678], "<u4").tobytes() + raw[4:]),
             "version 7": lambda: gzip.compress(raw[:4] + np.array([7], "<u4").tobytes() + raw[8:]),
             "degree 4": lambda: gzip.compress(raw[:12] + bytes([4]) + raw[13:]),
             "truncated body": lambda: gzip.compress(raw[:-5]),
             "version 1 inf": lambda: pack_file(tmp_path / "v1.spz", 1, 0, 0, v1).read_bytes()}
    v1 = random_fields(np.random.default_rng(2), 10, 1, 0)
    v1["positions"][3, 1] = np.inf
    path.write_bytes(edits[case]())
    with pytest.raises(SpzError) as err:
        load_spz(path)
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)


def test_missing_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(SpzError, match="nope.spz: cannot open"):
        load_spz(tmp_path / "nope.spz")


# ---------------------------------------------------------------- the writer's bytes, point by point

def _round(x: float) -> float:
    """std::round: half away from zero."""
    return math.copysign(math.floor(abs(x) + 0.5), x)


def _byte(x: float) -> int:
    return int(min(255.0, max(0.0, _round(x))))


def reference_encode(scene: GaussianScene) -> bytes:
    """The version-3 stream of the format description (nianticlabs/spz README, load-spz.cc's quantisers),
    one value at a time in Python floats: 12 fractional bits (fewer when the largest coordinate needs it),
    alpha round(255 o), colour round(255 (0.15 f_dc + 0.5)), scale round(16 (ln s + 10)), smallest-three
    rotations, SH round(128 f) + 128 in buckets of 8 (degree 1) or 16 (degrees 2, 3), bytes clamped."""
    n, k = len(scene), (scene.sh_degree + 1) ** 2
    m = max((abs(float(v)) for v in scene.means.ravel()), default=0.0)
    bits = 12 if m == 0 else min(12, math.floor(math.log2((2**23 - 1) / m)))
    while _round(m * 2.0**bits) > 2**23 - 1:
        bits -= 1
    out = bytearray(np.array([MAGIC, 3, n], "<u4").tobytes() + bytes([scene.sh_degree, bits, 0, 0]))
    for p in scene.means:
        for x in p:
            out += (int(_round(float(x) * 2.0**bits)) & 0xFFFFFF).to_bytes(3, "little")
    out += bytes(_byte(float(o) * 255.0) for o in scene.opacities)
    out += bytes(_byte(float(c) * (0.15 * 255.0) + 0.5 * 255.0) for c in scene.sh[:, 0, :].ravel())
    out += bytes(_byte((math.log(float(s)) + 10.0) * 16.0) for s in scene.scales.ravel())
    for w, x, y, z in scene.quats.astype(np.float64).tolist():
        norm = math.sqrt(((x * x + y * y) + z * z) + w * w)
        xyzw = [x / norm, y / norm, z / norm, w / norm]
        i = max(range(4), key=lambda j: (abs(xyzw[j]), -j))  # the first of equal magnitudes
        word = i
        for j in range(4):
            if j != i:  # the sign relative to a positive largest component: (c < 0) xor (largest < 0)
                negative = (xyzw[j] < 0) != (xyzw[i] < 0)
                word = word << 10 | negative << 9 | int(math.floor(511.0 * abs(xyzw[j]) / math.sqrt(0.5) + 0.5))
        out += (word & 0xFFFFFFFF).to_bytes(4, "little")
    for point in scene.sh:
        for j in range(1, k):
            bucket = 8 if j < 4 else 16
            for c in range(3):
                q = _round(float(point[j, c]) * 128.0) + 128.0
                out.append(int(min(255.0, max(0.0, math.floor((q + bucket // 2) / bucket) * bucket))))
    return bytes(out)


def tie_scene(rng: np.random.Generator, n: int, degree: int) -> GaussianScene:
    """Values on the writers' rounding ties (half steps of every field's quantiser, SH on both sides of 0,
    equal quaternion components) and random ones."""
    k = (degree + 1) ** 2
    base = random_scene(rng, n, degree)
    means = np.where(rng.random((n, 3)) < 0.5, (rng.integers(-40000, 40000, (n, 3)) + 0.5) / 4096, base.means)
    q = base.quats.astype(np.float64)
    q[: n // 4] = rng.choice([-0.5, 0.5], (n // 4, 4))
    q[n // 4: n // 2] = np.round(rng.normal(size=(n // 2 - n // 4, 4)))
    q[np.abs(q).sum(1) == 0] = [0, 0, 0, -1]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    sh = base.sh.copy()
    tie = rng.random(sh.shape) < 0.5
    sh[tie] = ((rng.integers(-200, 200, sh.shape) + 0.5) / 128)[tie]
    opac = np.where(rng.random(n) < 0.5, (rng.integers(0, 255, n) + 0.5) / 255, base.opacities)
    scales = np.where(rng.random((n, 3)) < 0.5, np.exp((rng.integers(-150, 250, (n, 3)) + 0.5) / 16 - 10),
                      base.scales)
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return GaussianScene(f32(means), f32(q), f32(scales), f32(opac), f32(sh[:, :k]), degree)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_writer_bytes_equal_the_format_description_point_by_point(tmp_path: Path, degree: int) -> None:
    """Rows split over many slices (``row_tasks``), ties of every quantiser: the bytes the description gives,
    and the file is their gzip stream as ``gzip.compress`` writes it."""
    from scenesplat_stereo.scene import row_tasks

    scene = tie_scene(np.random.default_rng(10 + degree), 3000, degree)
    expected = reference_encode(scene)
    original = row_tasks.ROWS_PER_TASK
    try:
        row_tasks.ROWS_PER_TASK = 512  # many slices of a small scene
        assert encode_spz(scene) == expected
        # the file: the standard library's gzip of those bytes (level 6, mtime 0), though deflated block by block
        assert save_spz(scene, tmp_path / "t.spz").read_bytes() == gzip.compress(expected, 6, mtime=0)
    finally:
        row_tasks.ROWS_PER_TASK = original


@pytest.mark.parametrize("degree", [0, 2])
@pytest.mark.parametrize("piece", [1000, 4096, 1 << 17])
def test_parallel_deflate_decodes_to_the_same_stream(tmp_path: Path, degree: int, piece: int, monkeypatch) -> None:
    """``save_spz(..., parallel=True)``: the gzip header and trailer of the one-stream file, and a deflate stream
    that GNU gzip's own inflate (not zlib's) and the standard library's both decode to the bytes the format
    description gives; pieces much smaller than the stream, a piece ending where the stream does, one piece
    for the whole, and pieces ending inside blocks."""
    from scenesplat_stereo.scene import row_tasks, spz

    monkeypatch.setattr(spz, "DEFLATE_PIECE", piece)
    monkeypatch.setattr(row_tasks, "ROWS_PER_TASK", 512)
    for n in (0, 1, 1228, 3000):
        scene = tie_scene(np.random.default_rng(20 + degree), n, degree) if n else random_scene(
            np.random.default_rng(0), 0, degree)
        expected = reference_encode(scene)
        if piece == 4096 and n == 1228 and degree == 0:
            assert len(expected) == 6 * piece  # 16 + 20 n bytes: the last piece ends where the stream does
        data = save_spz(scene, tmp_path / "p.spz", parallel=True).read_bytes()
        one = gzip.compress(expected, 6, mtime=0)
        assert data[:10] == one[:10] and data[-8:] == one[-8:]
        assert gzip.decompress(data) == expected
        if shutil.which("gzip"):
            assert subprocess.run(["gzip", "-dc"], input=data, capture_output=True, check=True).stdout == expected
        pieces = -(-len(expected) // piece)
        assert len(data) <= len(one) + 400 * pieces  # each piece: a new block's code tables and a sync flush
        assert (pieces > 1) == (data != one)

def zstd_compress(data: bytes) -> bytes:
    """One zstd frame of ``data`` through the system's libzstd (the test's own binding)."""
    lib = ctypes.CDLL(ctypes.util.find_library("zstd"))
    lib.ZSTD_compressBound.restype, lib.ZSTD_compressBound.argtypes = ctypes.c_size_t, [ctypes.c_size_t]
    lib.ZSTD_compress.restype = ctypes.c_size_t
    lib.ZSTD_compress.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_int]
    out = ctypes.create_string_buffer(lib.ZSTD_compressBound(len(data)))
    n = lib.ZSTD_compress(out, len(out), data, len(data), 3)
    return out.raw[:n]


def pack_v4(path: Path, degree: int, fbits: int, fields: dict, extension: bytes = b"") -> Path:
    """A version-4 .spz as load-spz.cc lays it out: 32-byte header, extension bytes, stream table, zstd frames."""
    n = len(fields["alphas"])
    pos = np.asarray(fields["positions"], dtype=np.int64) & 0xFFFFFF
    blocks = [np.stack([(pos >> s) & 0xFF for s in (0, 8, 16)], -1).astype(np.uint8), fields["alphas"],
              fields["colours"], fields["scales"], fields["rotations"], fields["sh"]]
    raw = [np.ascontiguousarray(b, dtype=np.uint8).tobytes() for b in blocks]
    raw = [b for b in raw if b]
    frames = [zstd_compress(b) for b in raw]
    toc = 32 + len(extension)
    header = np.array([MAGIC, 4, n], "<u4").tobytes() + bytes([degree, fbits, 2 if extension else 0, len(raw)]) \
        + np.array([toc], "<u4").tobytes() + bytes(12)
    table = b"".join(np.array([len(f), len(b)], "<u8").tobytes() for f, b in zip(frames, raw))
    path.write_bytes(header + extension + table + b"".join(frames))
    return path


needs_zstd = pytest.mark.skipif(ctypes.util.find_library("zstd") is None, reason="needs the system's libzstd")


@needs_zstd
@pytest.mark.parametrize("degree,extension", [(0, b""), (2, b"\x07extension bytes")])
def test_version_4_matches_the_format_description(tmp_path: Path, degree: int, extension: bytes) -> None:
    fields = random_fields(np.random.default_rng(40 + degree), 120, 3, degree)
    path = pack_v4(tmp_path / "v4.spz", degree, 11, fields, extension)
    scene, ref = load_spz(path), reference_decode(3, degree, 11, fields)
    assert (len(scene), scene.sh_degree) == (120, degree) == scene_info(path)
    np.testing.assert_array_equal(scene.means, ref["means"].astype(np.float32))
    np.testing.assert_allclose(scene.scales, ref["scales"], rtol=2 * EPS32)
    np.testing.assert_allclose(scene.sh, ref["sh"], atol=4 * EPS32 * np.abs(ref["sh"]).max())
    np.testing.assert_allclose(scene.quats, ref["quats"], atol=4 * EPS32)


@needs_zstd
@pytest.mark.parametrize("case,message", [
    ("truncated", "stream table: compressed sizes add up to"),
    ("corrupt frame", "stream alphas: corrupt zstd data"),
    ("stream count", "header numStreams 5 / tocByteOffset 32: expected 6 streams"),
])
def test_bad_version_4_files(tmp_path: Path, case: str, message: str) -> None:
    path = pack_v4(tmp_path / "bad.spz", 1, 12, random_fields(np.random.default_rng(5), 30, 3, 1))
    raw = bytearray(path.read_bytes())
    table = np.frombuffer(bytes(raw[32:32 + 6 * 16]), "<u8").reshape(6, 2)
    if case == "truncated":
        raw = raw[:-3]
    elif case == "corrupt frame":
        start = 32 + 6 * 16 + int(table[0, 0])
        raw[start:start + 4] = b"\0\0\0\0"  # the second frame's magic number
    else:
        raw[15] = 5
    path.write_bytes(bytes(raw))
    with pytest.raises(SpzError) as err:
        load_spz(path)
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)




@needs_zstd
@pytest.mark.skipif(not SPLAT_TRANSFORM.is_file() or shutil.which("node") is None,
                    reason="needs node and `npm ci` in scripts/checks/viewer (splat-transform 3.7.0)")
def test_splat_transforms_version_4_reads_as_its_version_3(tmp_path: Path) -> None:
    """splat-transform writes .spz through Niantic's library (WebAssembly); version 4 is its default."""
    from scenesplat_stereo.scene.gaussians import save_ply

    save_ply(random_scene(np.random.default_rng(7), 300, 3), tmp_path / "s.ply")
    for v in ("3", "4"):
        subprocess.run(["node", str(SPLAT_TRANSFORM), "-w", "--spz-version", v, str(tmp_path / "s.ply"),
                        str(tmp_path / f"v{v}.spz")], check=True, capture_output=True)
    assert (tmp_path / "v4.spz").read_bytes()[:4] == b"NGSP"
    a, b = load_spz(tmp_path / "v3.spz"), load_spz(tmp_path / "v4.spz")
    for name in ("means", "quats", "scales", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
