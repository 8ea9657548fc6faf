"""Tests of scenesplat_stereo.scene.gaussians on the PlayCanvas/SuperSplat compressed .ply: synthetic files
against a float64 decode written from the format description, and the real guitar pair in ../shared/data
(compressed vs its INRIA decode) within the format's quantisation.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.scene.gaussians import PlyError, load_ply, read_ply_header
from tests.support.ply_helpers import C0, EPS32, assert_matches_reference, write_ply

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
