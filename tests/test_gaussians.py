"""Tests of scenesplat_stereo.gaussians: GaussianScene, INRIA and compressed .ply reading, writing.

Expected values come from a float64 reference decode written here from SPEC section 1 and the
compressed-PLY format description (not from the module's output), and files are written by a small
independent PLY writer in this file.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.gaussians import (
    GaussianScene, PlyError, PlyRepairWarning, load_ply, read_ply_header, save_ply,
)

C0 = 0.28209479177387814
EPS32 = 2.0**-24  # unit roundoff of float32 (half an ulp at 1)
NPTYPE = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
          "float": "f4", "double": "f8"}


# ---------------------------------------------------------------- an independent PLY writer

def write_ply(path: Path, elements: list, fmt: str = "binary_little_endian", trailing: bytes = b"") -> Path:
    """elements: [(name, [(prop, ply_type, values[N]), ...]), ...] written in that order."""
    lines = ["ply", f"format {fmt} 1.0", "comment written by test_gaussians"]
    body = []
    for name, props in elements:
        n = len(props[0][2])
        lines.append(f"element {name} {n}")
        lines += [f"property {t} {p}" for p, t, _ in props]
        if fmt == "ascii":
            cols = [[repr(float(x)) if NPTYPE[t][0] == "f" else str(int(x)) for x in v] for _, t, v in props]
            body += [(" ".join(row) + "\n").encode() for row in zip(*cols)]
        else:
            bo = "<" if fmt == "binary_little_endian" else ">"
            arr = np.empty(n, dtype=[(p, bo + NPTYPE[t]) for p, t, _ in props])
            for p, _, v in props:
                arr[p] = v
            body.append(arr.tobytes())
    lines.append("end_header\n")
    path.write_bytes("\n".join(lines).encode() + b"".join(body) + trailing)
    return path


def inria_names(degree: int, normals: bool = True) -> list[str]:
    """The INRIA property order (3DGS `construct_list_of_attributes`, gsplat and nerfstudio exports)."""
    rest = [f"f_rest_{i}" for i in range(3 * ((degree + 1) ** 2 - 1))]
    return (["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"] + rest
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def random_raw(rng: np.random.Generator, n: int, degree: int) -> dict[str, np.ndarray]:
    """File-space values (logit opacity, log scales, non-unit wxyz), float32-representable."""
    raw = {}
    for name in inria_names(degree):
        if name == "opacity":
            v = rng.normal(0, 3, n)
        elif name.startswith("scale_"):
            v = rng.uniform(-7, 1, n)
        elif name.startswith("f_rest_"):
            v = rng.normal(0, 0.3, n)
        else:
            v = rng.normal(0, 1.5, n)
        raw[name] = v.astype(np.float32).astype(np.float64)
    return raw


def inria_props(raw: dict, order: list[str], types: dict | None = None) -> list:
    return [("vertex", [(p, (types or {}).get(p, "float"), raw[p]) for p in order])]


def reference_decode(raw: dict, degree: int) -> dict[str, np.ndarray]:
    """SPEC section 1, in float64 with explicit loops for the channel-major f_rest."""
    n, k = len(raw["x"]), (degree + 1) ** 2
    q = np.stack([raw[f"rot_{i}"] for i in range(4)], 1)
    sh = np.zeros((n, k, 3))
    for c in range(3):
        sh[:, 0, c] = raw[f"f_dc_{c}"]
        for j in range(1, k):
            sh[:, j, c] = raw[f"f_rest_{c * (k - 1) + j - 1}"]
    return {"means": np.stack([raw["x"], raw["y"], raw["z"]], 1),
            "quats": q / np.linalg.norm(q, axis=1, keepdims=True),
            "scales": np.exp(np.stack([raw[f"scale_{i}"] for i in range(3)], 1)),
            "opacities": 1.0 / (1.0 + np.exp(-raw["opacity"])), "sh": sh}


def assert_matches_reference(scene: GaussianScene, ref: dict) -> None:
    """Loaded float32 values equal the float64 reference rounded to float32 (within its rounding)."""
    assert scene.means.dtype == np.float32 and len(scene) == len(ref["means"])
    np.testing.assert_array_equal(scene.means, ref["means"].astype(np.float32))
    np.testing.assert_array_equal(scene.sh, ref["sh"].astype(np.float32))
    np.testing.assert_allclose(scene.quats, ref["quats"], rtol=0, atol=4 * EPS32)
    np.testing.assert_allclose(scene.opacities, ref["opacities"], rtol=0, atol=2 * EPS32)
    np.testing.assert_allclose(scene.scales, ref["scales"], rtol=2 * EPS32, atol=0)


def random_scene(rng: np.random.Generator, n: int, degree: int) -> GaussianScene:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    o = rng.uniform(0, 1, n)
    o[: min(n, 2)] = [0.0, 1.0][: min(n, 2)]  # the extremes must survive the logit
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return GaussianScene(f32(rng.normal(0, 3, (n, 3))), f32(q), f32(np.exp(rng.uniform(-9, 4, (n, 3)))),
                         f32(o), f32(rng.normal(0, 0.5, (n, (degree + 1) ** 2, 3))), degree)


# ---------------------------------------------------------------- save / load round trip

@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_every_sh_degree(tmp_path: Path, degree: int) -> None:
    scene = random_scene(np.random.default_rng(degree), 300, degree)
    path = save_ply(scene, tmp_path / "s.ply")
    # The file is the standard INRIA layout: float32 little-endian in the standard property order.
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    assert re.findall(rb"property float (\S+)", head) == [p.encode() for p in inria_names(degree)]
    assert b"format binary_little_endian 1.0" in head and b"element vertex 300" in head
    table = np.frombuffer(body, "<f4").reshape(300, -1)
    assert np.isfinite(table).all()  # opacity 0 and 1 give finite (clipped) logits
    np.testing.assert_array_equal(table[:, 3:6], 0)  # normals
    back = load_ply(path)
    assert back.sh_degree == degree and len(back) == 300
    # Bit-exact for the float32 values stored as they are.
    for name in ("means", "quats", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(scene, name))
    # Through logit / log in float64 and float32 storage: the stored value has relative error <= EPS32,
    # sigmoid' <= 1/4 and |l| sigmoid'(l) <= 0.224, exp' = exp, and the result is rounded once more.
    o = np.clip(scene.opacities.astype(np.float64), 1e-7, 1 - 1e-7)
    assert np.abs(back.opacities - o).max() <= EPS32
    assert back.opacities[0] < 1e-6 and back.opacities[1] > 1 - 1e-6
    s = scene.scales.astype(np.float64)
    rel = np.abs(back.scales / s - 1)
    assert (rel <= (np.abs(np.log(s)) + 1) * EPS32 * 1.001).all()


@pytest.mark.parametrize("n", [0, 1])
def test_round_trip_empty_and_single(tmp_path: Path, n: int) -> None:
    scene = random_scene(np.random.default_rng(7), n, 1)
    back = load_ply(save_ply(scene, tmp_path / "s.ply"))
    assert len(back) == n and back.sh.shape == (n, 4, 3)
    np.testing.assert_array_equal(back.means, scene.means)


def test_save_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1)
    path = save_ply(random_scene(rng, 10, 0), tmp_path / "s.ply")
    before = path.read_bytes()
    save_ply(random_scene(rng, 20, 2), path)  # overwriting works
    assert len(load_ply(path)) == 20 and os.listdir(tmp_path) == ["s.ply"]
    before = path.read_bytes()

    def fail(fd: int) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError, match="disk full"):
        save_ply(random_scene(rng, 5, 0), path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["s.ply"]


# ---------------------------------------------------------------- INRIA reading

@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("degree", [1, 3])
def test_inria_formats_match_reference(tmp_path: Path, fmt: str, degree: int) -> None:
    raw = random_raw(np.random.default_rng(degree), 37, degree)
    path = write_ply(tmp_path / "a.ply", inria_props(raw, inria_names(degree)), fmt)
    assert_matches_reference(load_ply(path), reference_decode(raw, degree))


def test_inria_any_order_types_extra_properties(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    raw = random_raw(rng, 41, 2)
    raw["x"] = rng.normal(size=41)  # stored as double: not float32-representable
    raw["f_dc_1"] = rng.integers(0, 256, 41).astype(np.float64)
    raw["rot_2"] = rng.integers(-300, 300, 41).astype(np.float64)
    raw["red"] = rng.integers(0, 256, 41).astype(np.float64)
    raw["filter_3D"] = rng.normal(size=41)
    order = inria_names(2, normals=False) + ["red", "filter_3D"]
    rng.shuffle(order)
    types = {"x": "double", "opacity": "double", "f_dc_1": "uchar", "rot_2": "short", "red": "uchar"}
    path = write_ply(tmp_path / "a.ply", inria_props(raw, order, types))
    scene = load_ply(path)
    ref = reference_decode(raw, 2)
    assert_matches_reference(scene, ref)


def test_inria_element_before_vertex_and_crlf_header(tmp_path: Path) -> None:
    raw = random_raw(np.random.default_rng(4), 9, 0)
    other = ("camera", [("fx", "double", np.arange(3.0)), ("id", "uchar", np.arange(3))])
    path = write_ply(tmp_path / "a.ply", [other] + inria_props(raw, inria_names(0)))
    assert_matches_reference(load_ply(path), reference_decode(raw, 0))
    head, body = path.read_bytes().split(b"end_header\n", 1)
    crlf = tmp_path / "crlf.ply"
    crlf.write_bytes(head.replace(b"\n", b"\r\n") + b"end_header\r\n" + body)
    assert_matches_reference(load_ply(crlf), reference_decode(raw, 0))


def test_quaternions_normalised_and_unit_ones_kept(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    # A float32 unit quaternion that float64 renormalisation would move by an ulp must be kept as stored.
    unit = rng.normal(size=(1000, 4))
    unit = (unit / np.linalg.norm(unit, axis=1, keepdims=True)).astype(np.float32)
    n64 = np.linalg.norm(unit.astype(np.float64), axis=1, keepdims=True)
    moved = unit[((unit / n64).astype(np.float32) != unit).any(1)][0]
    q = np.array([[2, 0, 0, 0], [0, 0, -3, 4], [1e-30, 0, 0, 0], moved], dtype=np.float64)
    raw = random_raw(rng, 4, 0)
    for i in range(4):
        raw[f"rot_{i}"] = q[:, i]
    scene = load_ply(write_ply(tmp_path / "q.ply", inria_props(raw, inria_names(0))))
    np.testing.assert_array_equal(scene.quats, np.float32([[1, 0, 0, 0], [0, 0, -0.6, 0.8], [1, 0, 0, 0],
                                                           moved]))


# ---------------------------------------------------------------- bad input

def _valid(tmp_path: Path, **kw) -> Path:
    raw = random_raw(np.random.default_rng(6), 5, 1)
    return write_ply(tmp_path / "v.ply", inria_props(raw, inria_names(1)), **kw)


def _header_edit(tmp_path: Path, old: bytes, new: bytes) -> Path:
    p = _valid(tmp_path)
    data = p.read_bytes()
    assert old in data
    p.write_bytes(data.replace(old, new, 1))
    return p


BAD_FILES = {
    "missing file": (lambda t: t / "absent.ply", "cannot open"),
    "not a ply": (lambda t: (t / "x.ply").write_text("hello\nworld\n") and t / "x.ply", "not a PLY"),
    "random bytes": (lambda t: (t / "r.ply").write_bytes(np.random.default_rng(0).bytes(5000))
                     and t / "r.ply", "not a PLY"),
    "no end_header": (lambda t: (t / "h.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\n")
                      and t / "h.ply", "end_header"),
    "unsupported format": (lambda t: _header_edit(t, b"binary_little_endian", b"binary_middle_endian"),
                           "unsupported format 'binary_middle_endian'"),
    "no format line": (lambda t: _header_edit(t, b"format binary_little_endian 1.0\n", b""), "no 'format'"),
    "unknown type": (lambda t: _header_edit(t, b"property float y\n", b"property half y\n"), "'y'"),
    "duplicate property": (lambda t: _header_edit(t, b"property float nx\n", b"property float x\n"),
                           "'x' is declared twice"),
    "garbage header line": (lambda t: _header_edit(t, b"comment", b"bogus"), "malformed header line"),
    "no vertex element": (lambda t: _header_edit(t, b"element vertex", b"element points"),
                          "no element 'vertex'"),
    "list property": (lambda t: _header_edit(t, b"property float nx\n",
                                             b"property list uchar int nx\n"), "list properties"),
    "truncated binary": (lambda t: (p := _valid(t)).write_bytes(p.read_bytes()[:-7]) and p,
                         "truncated: element 'vertex' needs"),
    "truncated ascii": (lambda t: (p := _valid(t, fmt="ascii")).write_bytes(
        b"\n".join(p.read_bytes().split(b"\n")[:-2]) + b"\n") and p,
        "truncated: element 'vertex' needs 5 lines"),
    "ascii short row": (lambda t: (p := _valid(t, fmt="ascii")).write_bytes(
        p.read_bytes().rsplit(b" ", 1)[0] + b"\n") and p, "row 4 has"),
    "ascii non-numeric": (lambda t: (p := _valid(t, fmt="ascii")).write_bytes(
        p.read_bytes()[:-3] + b"zz\n") and p, "non-numeric"),
    "wrong f_rest count": (lambda t: _header_edit(t, b"property float f_rest_8\n", b""),
                           "8 f_rest_* properties; expected 0, 9, 24 or 45"),
    "f_rest gap": (lambda t: _header_edit(t, b"property float f_rest_8\n", b"property float f_rest_9\n"),
                   "unexpected ['f_rest_9'], missing ['f_rest_8']"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_files_raise_ply_error(tmp_path: Path, case: str) -> None:
    make, message = BAD_FILES[case]
    path = make(tmp_path)
    with pytest.raises(PlyError) as err:
        load_ply(path)
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize("prop", ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0",
                                  "rot_1", "rot_2", "rot_3", "f_dc_0", "f_dc_1", "f_dc_2"])
def test_missing_required_property(tmp_path: Path, prop: str) -> None:
    raw = random_raw(np.random.default_rng(8), 5, 0)
    path = write_ply(tmp_path / "m.ply", inria_props(raw, [p for p in inria_names(0) if p != prop]))
    with pytest.raises(PlyError, match=re.escape(prop)) as err:
        load_ply(path)
    assert str(path) in str(err.value) and "lacks required properties" in str(err.value)


def test_trailing_bytes_warn(tmp_path: Path) -> None:
    raw = random_raw(np.random.default_rng(9), 5, 0)
    path = write_ply(tmp_path / "t.ply", inria_props(raw, inria_names(0)), trailing=b"\0" * 13)
    with pytest.warns(PlyRepairWarning, match="13 bytes after the last element"):
        assert_matches_reference(load_ply(path), reference_decode(raw, 0))


# ---------------------------------------------------------------- repairs

def test_bad_rows_dropped_with_counts(tmp_path: Path) -> None:
    raw = random_raw(np.random.default_rng(10), 10, 1)
    raw["x"][1] = np.nan
    raw["f_rest_3"][2] = np.inf
    raw["opacity"][3] = -np.inf
    raw["scale_0"][7] = -np.inf  # non-finite before exp: counted as non-finite
    for i in range(4):
        raw[f"rot_{i}"][4] = 0.0
    raw["scale_1"][5] = -200.0  # exp underflows to 0 in float32
    raw["scale_2"][6] = 200.0  # exp overflows to inf in float32
    raw["scale_0"][8] = -100.0  # 3.7e-44, a float32 subnormal: squares to 0, counted as a zero scale
    raw["scale_1"][9] = -80.0  # 1.8e-35, a normal float32: kept
    path = write_ply(tmp_path / "bad.ply", inria_props(raw, inria_names(1)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_ply(path)
    assert len(caught) == 1 and caught[0].category is PlyRepairWarning
    msg = str(caught[0].message)
    assert str(path) in msg and "8 of 10 Gaussians" in msg
    assert "4 with non-finite values" in msg and "1 with zero-norm quaternions" in msg
    assert "3 with zero or non-finite scales" in msg
    keep = [0, 9]
    ref = reference_decode({k: v[keep] for k, v in raw.items()}, 1)
    assert_matches_reference(scene, ref)
    with pytest.raises(PlyError, match="8 of 10 Gaussians.*strict=True"):
        load_ply(path, strict=True)


def test_clean_file_loads_strict_without_warning(tmp_path: Path) -> None:
    raw = random_raw(np.random.default_rng(11), 20, 0)
    path = write_ply(tmp_path / "ok.ply", inria_props(raw, inria_names(0)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(load_ply(path, strict=True)) == 20


# ---------------------------------------------------------------- compressed layout

CHUNK_BOX = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y",
             "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
CHUNK_RGB = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]


def compressed_elements(chunks: np.ndarray, codes: dict, colour_ranges: bool, sh: np.ndarray | None) -> list:
    """chunks [C, 12 or 18] float; codes: per-splat integer fields -> packed uint32 per the format."""
    pos = (codes["px"] << 21) | (codes["py"] << 11) | codes["pz"]
    scl = (codes["sx"] << 21) | (codes["sy"] << 11) | codes["sz"]
    rot = (codes["largest"] << 30) | (codes["qa"] << 20) | (codes["qb"] << 10) | codes["qc"]
    col = (codes["r"] << 24) | (codes["g"] << 16) | (codes["b"] << 8) | codes["a"]
    names = CHUNK_BOX + (CHUNK_RGB if colour_ranges else [])
    packed = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
    els = [("chunk", [(p, "float", chunks[:, i]) for i, p in enumerate(names)]),
           ("vertex", [(p, "uint", v) for p, v in zip(packed, [pos, rot, scl, col])])]
    if sh is not None:
        els.append(("sh", [(f"f_rest_{i}", "uchar", sh[:, i]) for i in range(sh.shape[1])]))
    return els


def random_codes(rng: np.random.Generator, n: int) -> dict:
    bits = {"px": 11, "py": 10, "pz": 11, "sx": 11, "sy": 10, "sz": 11, "qa": 10, "qb": 10, "qc": 10,
            "r": 8, "g": 8, "b": 8, "a": 8, "largest": 2}
    return {k: rng.integers(0, 1 << b, n, dtype=np.uint64).astype(np.uint32) for k, b in bits.items()}


def compressed_reference(chunks: np.ndarray, codes: dict, colour_ranges: bool, sh: np.ndarray | None) -> dict:
    """Decode written from the format description, one splat at a time, in float64."""
    n = len(codes["px"])
    out = {k: [] for k in ("means", "quats", "scales", "opacities", "sh")}
    for i in range(n):
        c = chunks[i // 256].astype(np.float64)
        t = np.array([codes["px"][i] / 2047, codes["py"][i] / 1023, codes["pz"][i] / 2047])
        out["means"].append(c[0:3] + (c[3:6] - c[0:3]) * t)
        t = np.array([codes["sx"][i] / 2047, codes["sy"][i] / 1023, codes["sz"][i] / 2047])
        out["scales"].append(np.exp(c[6:9] + (c[9:12] - c[6:9]) * t))
        others = [(codes[k][i] / 1023 - 0.5) * np.sqrt(2) for k in ("qa", "qb", "qc")]
        big = np.sqrt(max(0.0, 1 - sum(o * o for o in others)))
        q = others[:]
        q.insert(int(codes["largest"][i]), big)
        out["quats"].append(np.array(q) / np.linalg.norm(q))
        rgb = np.array([codes[k][i] / 255 for k in "rgb"])
        if colour_ranges:
            rgb = c[12:15] + (c[15:18] - c[12:15]) * rgb
        out["opacities"].append(codes["a"][i] / 255)
        k = 1 if sh is None else 1 + sh.shape[1] // 3
        coeffs = np.zeros((k, 3))
        coeffs[0] = (rgb - 0.5) / C0
        for j in range(1, k):
            for ch in range(3):
                q8 = int(sh[i, ch * (k - 1) + j - 1])
                coeffs[j, ch] = -4.0 if q8 == 0 else 4.0 if q8 == 255 else ((q8 + 0.5) / 256 - 0.5) * 8
        out["sh"].append(coeffs)
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("colour_ranges,sh_props", [(True, 0), (False, 9), (True, 45)])
def test_compressed_matches_reference(tmp_path: Path, colour_ranges: bool, sh_props: int) -> None:
    rng = np.random.default_rng(sh_props)
    n = 300  # two chunks, the second partial
    lo = rng.uniform(-3, 0, (2, 3))
    box = [lo, lo + rng.uniform(0.1, 3, (2, 3)), np.full((2, 3), -6.0), np.full((2, 3), 1.0)]
    rgb = [rng.uniform(-0.2, 0.3, (2, 3)), rng.uniform(0.7, 1.2, (2, 3))] if colour_ranges else []
    chunks = np.concatenate(box + rgb, 1).astype(np.float32)
    codes = random_codes(rng, n)
    codes["qa"][:3] = [1023, 0, 512]  # corner cases of the 10-bit range
    sh = rng.integers(0, 256, (n, sh_props)).astype(np.uint8) if sh_props else None
    if sh is not None:
        sh[:2, :] = [[0], [255]]
    path = write_ply(tmp_path / "c.ply", compressed_elements(chunks, codes, colour_ranges, sh))
    header = read_ply_header(path)
    assert header.layout == "compressed" and header.num_gaussians == n
    assert header.sh_degree == {0: 0, 9: 1, 45: 3}[sh_props]
    assert_matches_reference(load_ply(path), compressed_reference(chunks, codes, colour_ranges, sh))


def test_compressed_encoding_error_within_quantisation(tmp_path: Path) -> None:
    """Encode known Gaussians (smallest-three quaternions, unorm boxes) and bound the decode error."""
    rng = np.random.default_rng(12)
    n = 256
    means = rng.uniform(-2, 2, (n, 3))
    log_s = rng.uniform(-5, 0, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.abs(q).argmax(1)
    q *= np.sign(q[np.arange(n), largest])[:, None]
    lo, hi, slo, shi = means.min(0), means.max(0), log_s.min(0), log_s.max(0)
    unorm = lambda t, bits: np.floor(t * ((1 << bits) - 1) + 0.5).astype(np.uint32)  # noqa: E731
    widths = [11, 10, 11]
    codes = {}
    for j, a in enumerate("xyz"):
        codes[f"p{a}"] = unorm((means[:, j] - lo[j]) / (hi[j] - lo[j]), widths[j])
        codes[f"s{a}"] = unorm((log_s[:, j] - slo[j]) / (shi[j] - slo[j]), widths[j])
    others = np.array([[q[i, j] for j in range(4) if j != largest[i]] for i in range(n)])
    for j, k in enumerate(("qa", "qb", "qc")):
        codes[k] = unorm(others[:, j] / np.sqrt(2) + 0.5, 10)
    codes["largest"] = largest.astype(np.uint32)
    for k in "rgba":
        codes[k] = np.full(n, 128, np.uint32)
    chunks = np.concatenate([lo, hi, slo, shi])[None].astype(np.float32)
    scene = load_ply(write_ply(tmp_path / "e.ply", compressed_elements(chunks, codes, False, None)))
    c = chunks[0].astype(np.float64)
    half_steps = (c[3:6] - c[0:3]) / (2 * (2.0 ** np.array(widths) - 1))
    assert (np.abs(scene.means - means) <= half_steps + 4 * EPS32 * 2).all()
    half_log = (c[9:12] - c[6:9]) / (2 * (2.0 ** np.array(widths) - 1))
    assert (np.abs(np.log(scene.scales.astype(np.float64)) - log_s) <= half_log + 1e-6).all()
    # Each small component is off by <= h = sqrt(2)/(2*1023); the largest m >= 1/2 by <= 3h (|dm| <=
    # h (|a|+|b|+|c|)/m <= h sqrt(3 (1 - m^2))/m); normalising at most doubles the distance.
    h = np.sqrt(2) / (2 * 1023)
    assert (np.linalg.norm(scene.quats - q, axis=1) <= 2 * np.sqrt(12) * h).all()


@pytest.mark.parametrize("case,message", [
    ("chunk count", "element 'chunk' has 1 rows; 300 vertices need 2"),
    ("missing packed_color", "lacks required properties packed_color"),
    ("missing min_scale_y", "lacks required properties min_scale_y"),
    ("partial colour ranges", "lacks ['max_b']"),
    ("float packed", "'packed_scale' must be 32-bit unsigned"),
    ("sh count", "7 f_rest_* properties"),
])
def test_bad_compressed_files(tmp_path: Path, case: str, message: str) -> None:
    rng = np.random.default_rng(13)
    chunks = rng.uniform(0, 1, (2, 18)).astype(np.float32)
    els = compressed_elements(chunks, random_codes(rng, 300), True, None)
    chunk_props, vertex_props = els[0][1], els[1][1]
    if case == "chunk count":
        els[0] = ("chunk", [(p, t, v[:1]) for p, t, v in chunk_props])
    elif case == "missing packed_color":
        els[1] = ("vertex", vertex_props[:3])
    elif case == "missing min_scale_y":
        els[0] = ("chunk", [x for x in chunk_props if x[0] != "min_scale_y"])
    elif case == "partial colour ranges":
        els[0] = ("chunk", chunk_props[:-1])
    elif case == "float packed":
        els[1] = ("vertex", [(p, "float" if p == "packed_scale" else t, v) for p, t, v in vertex_props])
    else:
        els.append(("sh", [(f"f_rest_{i}", "uchar", np.zeros(300)) for i in range(7)]))
    path = write_ply(tmp_path / "bad.ply", els)
    with pytest.raises(PlyError) as err:
        load_ply(path)
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)


# ---------------------------------------------------------------- GaussianScene

def test_scene_helpers() -> None:
    scene = random_scene(np.random.default_rng(14), 50, 2)
    assert len(scene) == scene.num_gaussians == 50
    lo, hi = scene.bounds()
    np.testing.assert_array_equal(lo, np.min(scene.means, axis=0))
    np.testing.assert_array_equal(hi, np.max(scene.means, axis=0))
    np.testing.assert_allclose(scene.median(), [np.median(scene.means[:, j]) for j in range(3)], rtol=1e-6)
    mask = scene.opacities > 0.5
    sub = scene.subset(mask)
    assert len(sub) == mask.sum() and sub.sh_degree == 2
    np.testing.assert_array_equal(sub.sh, scene.sh[mask])
    idx = scene.subset([4, 2, 2])
    np.testing.assert_array_equal(idx.quats, scene.quats[[4, 2, 2]])
    assert len(scene.subset(slice(10, 20))) == 10 and len(scene.subset([])) == 0
    idx.means[0] = 99.0  # a copy
    assert scene.means[4, 0] != 99.0
    with pytest.raises(ValueError, match="bool mask"):
        scene.subset(mask[:-1])
    empty = scene.subset(np.zeros(50, bool))
    with pytest.raises(ValueError, match="empty scene"):
        empty.bounds()


def test_to_torch() -> None:
    torch = pytest.importorskip("torch")
    scene = random_scene(np.random.default_rng(15), 8, 1)
    t = scene.to_torch("cpu")
    assert set(t) == {"means", "quats", "scales", "opacities", "colors"}
    assert all(v.dtype == torch.float32 and v.device.type == "cpu" for v in t.values())
    assert t["colors"].shape == (8, 4, 3) and t["opacities"].shape == (8,)
    np.testing.assert_array_equal(t["scales"].numpy(), scene.scales)


def test_to_torch_feeds_rasterization() -> None:
    """The dict keys are rasterization's argument names (SPEC section 2); one Gaussian on the optical axis."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("warp")
    from scenesplat_stereo.raster import rasterization

    f32 = np.float32
    scene = GaussianScene(f32([[0, 0, 2]]), f32([[1, 0, 0, 0]]), f32([[0.2, 0.2, 0.2]]), f32([0.9]),
                          f32([[[0.5 / C0, 0, -0.5 / C0]]]), 0)  # colour (1, 0.5, 0)
    K = torch.tensor([[[16.0, 0, 8], [0, 16, 6], [0, 0, 1]]])
    rgb, alpha, _ = rasterization(**scene.to_torch(), viewmats=torch.eye(4)[None], Ks=K, width=16, height=12,
                                  sh_degree=0)
    assert rgb.shape == (1, 12, 16, 3) and alpha[0, 6, 8, 0] > 0.8 and alpha[0, 0, 0, 0] < 0.01
    np.testing.assert_allclose(rgb[0, 6, 8].numpy() / alpha[0, 6, 8].item(), [1, 0.5, 0], atol=1e-5)


@pytest.mark.parametrize("field,value,message", [
    ("means", np.zeros((5, 3)), "means must be a numpy float32 array"),
    ("quats", np.zeros((5, 3), np.float32), "quats must have shape [5, 4]"),
    ("sh", np.zeros((5, 1, 3), np.float32), "sh must have shape [5, 4, 3]"),
    ("sh_degree", 4, "sh_degree must be an int in 0..3"),
    ("quats", np.tile(np.float32([1, 0, 0, 0.1]), (5, 1)), "quats: 5 rows not unit norm"),
    ("scales", np.float32([[1, 1, 1]] * 4 + [[1, 0, 1]]), "scales: 1 rows not > 0"),
    ("opacities", np.float32([0, 1, 0.5, 1.5, -0.1]), "opacities: 2 rows outside [0, 1]"),
    ("means", np.float32([[0, 0, np.nan]] + [[0, 0, 0]] * 4), "means has 1 rows with non-finite"),
    ("opacities", [0.5] * 5, "opacities must be a numpy float32 array"),
])
def test_scene_validation(field: str, value, message: str) -> None:
    fields = dict(means=np.zeros((5, 3), np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (5, 1)),
                  scales=np.ones((5, 3), np.float32), opacities=np.full(5, 0.5, np.float32),
                  sh=np.zeros((5, 4, 3), np.float32), sh_degree=1)
    fields[field] = value
    with pytest.raises(ValueError, match=re.escape(message)):
        GaussianScene(**fields)


# ---------------------------------------------------------------- the real guitar pair

def _compressed_tables(path: Path) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Chunk ranges by name and the raw packed uint32 [N, 4], read by hand from the file."""
    data = path.read_bytes()
    head, _ = data.split(b"end_header\n", 1)
    offset = len(head) + len(b"end_header\n")
    text = head.decode()
    n_chunk = int(re.search(r"element chunk (\d+)", text).group(1))
    n = int(re.search(r"element vertex (\d+)", text).group(1))
    chunk_names = re.findall(r"property float (\w+)", text.split("element vertex")[0])
    chunks = np.frombuffer(data, "<f4", n_chunk * len(chunk_names), offset).reshape(n_chunk, -1)
    packed = np.frombuffer(data, "<u4", n * 4, offset + chunks.nbytes).reshape(n, 4)
    return {p: chunks[:, i].astype(np.float64) for i, p in enumerate(chunk_names)}, packed


@pytest.mark.real_data
def test_guitar_compressed_agrees_with_inria_decode(guitar_ply: Path, guitar_compressed_ply: Path) -> None:
    """point_cloud.ply is splat-transform's INRIA decode of guitar.compressed.ply (shared PROVENANCE.md).

    Both must agree within the format's quantisation (half a step of each field's bit width over its chunk
    range); since both decode the same bits, they must in fact agree to float32 rounding except the alpha
    bytes 0 and 255, which the INRIA file clips to logit(+-254.5/255).
    """
    a, b = load_ply(guitar_ply), load_ply(guitar_compressed_ply)
    ranges, packed = _compressed_tables(guitar_compressed_ply)
    n = len(packed)
    assert len(a) == len(b) == n == 90854 and a.sh_degree == b.sh_degree == 0
    ci = np.arange(n) // 256
    span = lambda lo, hi: np.stack([ranges[f"{hi}{s}"][ci] - ranges[f"{lo}{s}"][ci]  # noqa: E731
                                    for s in ("x", "y", "z")], 1)
    levels = 2.0 ** np.array([11, 10, 11]) - 1
    step_pos, step_log = span("min_", "max_") / levels, span("min_scale_", "max_scale_") / levels
    step_dc = np.stack([ranges[f"max_{c}"][ci] - ranges[f"min_{c}"][ci] for c in "rgb"], 1) / 255 / C0

    err = {"means": np.abs(a.means.astype(np.float64) - b.means),
           "log scales": np.abs(np.log(a.scales.astype(np.float64)) - np.log(b.scales.astype(np.float64))),
           "f_dc": np.abs(a.sh[:, 0].astype(np.float64) - b.sh[:, 0]),
           "opacities": np.abs(a.opacities.astype(np.float64) - b.opacities),
           "quats": np.minimum(np.linalg.norm(a.quats - b.quats, axis=1),
                               np.linalg.norm(a.quats + b.quats, axis=1))}
    rounding = {"means": 2 * EPS32 * np.abs(a.means), "f_dc": 2 * EPS32 * np.abs(a.sh[:, 0]),
                "log scales": 4 * EPS32 * np.maximum(1, np.abs(np.log(a.scales.astype(np.float64))))}
    # The format's bound: half a quantisation step (rotation: see test_compressed_encoding_error...).
    h_rot = np.sqrt(2) / (2 * 1023)
    assert (err["means"] <= step_pos / 2 + rounding["means"]).all()
    assert (err["log scales"] <= step_log / 2 + rounding["log scales"]).all()
    assert (err["f_dc"] <= step_dc / 2 + rounding["f_dc"]).all()
    assert (err["opacities"] <= 0.5 / 255 + 2 * EPS32).all()
    assert (err["quats"] <= 2 * np.sqrt(12) * h_rot).all()
    # The same bits decoded twice: float32 rounding only.
    for k in ("means", "log scales", "f_dc"):
        assert (err[k] <= rounding[k]).all(), k
    assert err["quats"].max() <= 8 * EPS32
    alpha = packed[:, 3] & 0xFF
    clipped = (alpha == 0) | (alpha == 255)
    assert clipped.any() and (err["opacities"][~clipped] <= 2 * EPS32).all()
    np.testing.assert_allclose(err["opacities"][clipped], 0.5 / 255, rtol=1e-4)
    print("guitar decode agreement (max abs error): "
          + ", ".join(f"{k} {v.max():.3g}" for k, v in err.items())
          + f"; unclipped opacities {err['opacities'][~clipped].max():.3g}; {clipped.sum()} clipped alphas")


@pytest.mark.real_data
def test_guitar_headers(guitar_ply: Path, guitar_compressed_ply: Path) -> None:
    h, hc = read_ply_header(guitar_ply), read_ply_header(guitar_compressed_ply)
    assert (h.layout, h.sh_degree, h.num_gaussians) == ("inria", 0, 90854)
    assert (hc.layout, hc.sh_degree, hc.num_gaussians) == ("compressed", 0, 90854)
    scene = load_ply(guitar_ply)
    np.testing.assert_allclose(scene.median(), [0.29, -1.13, 0.18], atol=0.01)  # PROVENANCE.md
