"""Tests of scenesplat_stereo.scene.gaussians: GaussianScene, INRIA .ply reading and writing, bad input.

Expected values come from a float64 reference decode written from SPEC section 1 (tests/support/ply_helpers.py),
not from the module's output, and files are written by an independent PLY writer there.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.scene.gaussians import GaussianScene, PlyError, PlyRepairWarning, load_ply, save_ply
from tests.support.ply_helpers import (C0, EPS32, assert_matches_reference, inria_names, inria_props, random_raw,
                                       random_scene, reference_decode, write_ply)

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
