"""Captures composed into rooms (scenesplat_stereo.build.compose): the object's metric size, upright orientation
and SH colours checked in float64 against formulas written here, the cameras' distances and aim, the build on a
composed teacher, refusals of bad captures, and the real guitar composed."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.build.compose import (
    FAMILIES,
    compose_teacher,
    measure_capture,
    read_capture,
)
from scenesplat_stereo.cli import main
from scenesplat_stereo.scene.gaussians import GaussianScene, load_ply, save_ply
from scenesplat_stereo.scene.harmonics import sh_basis
from scenesplat_stereo.scene.ply import PlyError
from scenesplat_stereo.scene.scene_files import load_scene
from scenesplat_stereo.scene.teachers import discover_teachers
from scenesplat_stereo.shards import webdataset as shards
from tests.support.bad_input import refusal, snapshot
from tests.support.ply_helpers import inria_names, inria_props, write_ply

BODY = 600  # Gaussians of the synthetic object; floaters come after them


def synthetic_capture(degree: int = 0, seed: int = 0) -> GaussianScene:
    """An asymmetric object in COLMAP axes (y down, arbitrary units): a 1 x 3 x 0.5 column standing along -y from
    y = 0 to y = -3, its top fifth pushed towards +x (a "head"), then floaters: 40 faint Gaussians near it and 5
    opaque ones 100 units away."""
    rng = np.random.default_rng(seed)
    body = rng.uniform([0.0, -3.0, 0.0], [1.0, 0.0, 0.5], (BODY, 3))
    body[body[:, 1] < -2.4, 0] += 0.8                                        # the head leans to +x
    faint = rng.uniform(-1, 2, (40, 3))
    far = rng.normal(size=(5, 3)) * 3 + [100.0, 0.0, 0.0]
    means = np.concatenate([body, faint, far])
    n = len(means)
    q = rng.normal(size=(n, 4))
    opacities = np.concatenate([rng.uniform(0.5, 1.0, BODY), np.full(40, 0.02), np.full(5, 0.9)])
    return GaussianScene(means.astype(np.float32), (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                         rng.uniform(0.01, 0.05, (n, 3)).astype(np.float32), opacities.astype(np.float32),
                         (rng.normal(size=(n, (degree + 1) ** 2, 3)) * 0.3).astype(np.float32), degree)


def weighted_quantile(x: np.ndarray, w: np.ndarray, q: float) -> float:
    """The smallest x whose cumulative weight (sorted) reaches q of the total: the inverted CDF, by hand."""
    order = np.argsort(x, kind="stable")
    cum = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cum, q * cum[-1])])


def composed(degree: int = 0, family: str = "tabletop", seed: int = 1, frames: int = 12):
    capture = measure_capture(synthetic_capture(degree), Path("synthetic.ply"))
    return capture, compose_teacher(capture, FAMILIES[family], np.random.default_rng(seed), frames, (64, 48), 2000)


@pytest.mark.parametrize("family", ["tabletop", "statue"])
def test_the_object_has_the_drawn_metric_size_and_the_floaters_are_gone(family):
    capture, c = composed(family=family)
    lo_size, hi_size = FAMILIES[family].size
    assert lo_size <= c.size <= hi_size and len(capture.scene) == BODY and capture.dropped == 45
    obj = c.scene.means[c.object_rows].astype(np.float64)
    w = c.scene.opacities[c.object_rows].astype(np.float64)
    sides = [weighted_quantile(obj[:, a], w, 0.99) - weighted_quantile(obj[:, a], w, 0.01) for a in range(3)]
    assert max(sides) == pytest.approx(c.size, rel=1e-5)
    src = synthetic_capture().means[:BODY].astype(np.float64)                 # world = k R p + offset, float64
    np.testing.assert_allclose(obj, c.scale * src @ c.R.T + c.offset, atol=1e-5 * max(1.0, c.size))
    np.testing.assert_allclose(np.log(c.scene.scales[c.object_rows]),
                               np.log(synthetic_capture().scales[:BODY]) + math.log(c.scale), atol=1e-5)
    low = weighted_quantile(obj[:, 2], w, 0.01)                               # standing on its support
    assert low == pytest.approx(0.0 if family == "statue" else c.centre[2] - 0.5 * (c.scale * 3.0), abs=0.05 * c.size)
    assert np.allclose(c.centre[:2], np.array(c.room_size[:2]) / 2)


def test_the_capture_stands_upright():
    """The capture's up (-y) ends along +z; its head (top fifth, leaning to +x) is the highest part."""
    _, c = composed(family="statue")
    np.testing.assert_allclose(c.R @ [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-12)
    obj = c.scene.means[c.object_rows].astype(np.float64)
    head = synthetic_capture().means[:BODY, 1] < -2.4
    assert obj[head, 2].min() > np.percentile(obj[~head, 2], 75)
    height = obj[:, 2].max() - obj[:, 2].min()
    assert height == pytest.approx(3.0 * c.scale, rel=0.02)                    # the 3-unit column is the height


def test_sh3_colour_seen_along_a_direction_is_unchanged_by_the_turn():
    """Colour of object Gaussian i along world direction d = the capture's colour along R^T d (float64, no render)."""
    capture, c = composed(degree=3, family="tabletop")
    src = synthetic_capture(3).sh[:BODY].astype(np.float64)
    new = c.scene.sh[c.object_rows].astype(np.float64)
    d = np.random.default_rng(5).normal(size=(BODY, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    seen = np.einsum("nk,nkc->nc", sh_basis(3, d), new)
    before = np.einsum("nk,nkc->nc", sh_basis(3, d @ c.R), src)
    np.testing.assert_allclose(seen, before, atol=1e-5)
    assert c.scene.sh_degree == 3 and capture.scene.sh_degree == 3


@pytest.mark.parametrize("family", ["tabletop", "statue"])
def test_cameras_look_at_the_object_from_the_family_distances_inside_the_room(family):
    _, c = composed(family=family, frames=16)
    eyes, axes = c.c2w[:, :3, 3], c.c2w[:, :3, 2]
    to_obj = c.centre - eyes
    dist = np.linalg.norm(to_obj, axis=1)
    lo, hi = FAMILIES[family].distance
    assert (dist >= max(lo, 0.75 * c.size) - 1e-9).all() and (dist <= hi + 1e-9).all()
    assert (dist >= c.distance[0] - 1e-9).all() and (dist <= c.distance[1] + 1e-9).all()
    nearest = max(lo, 0.75 * c.size)                                            # near end: the nearest quarter
    assert nearest <= c.distance[0] <= nearest + 0.25 * (hi - nearest) and c.distance[1] >= (nearest + hi) / 2
    cos = np.einsum("fi,fi->f", axes, to_obj) / dist
    assert (cos[c.looks_at] > 1 - 1e-9).all()                                  # the object at the image centre
    assert (~c.looks_at).sum() == 4 and (cos[~c.looks_at] < math.cos(math.radians(45))).all()
    assert (c.c2w[:, 2, 1] < 0).all()                                           # image down is world down
    assert (eyes > 0.3).all() and (eyes < np.array(c.room_size) - 0.3).all()
    fov = 2 * math.degrees(math.atan(0.5 * c.width / c.K[0, 0]))
    assert 60 <= fov <= 75


def write_capture(path: Path, degree: int = 0, **changes) -> Path:
    s = synthetic_capture(degree)
    for k, v in changes.items():
        setattr(s, k, v)
    save_ply(s, path)
    return path


def test_the_command_is_deterministic_and_its_teachers_build(tmp_path, capsys):
    capture = write_capture(tmp_path / "caps" / "column.ply", degree=1)
    argv = ["compose-teachers", "--captures", tmp_path / "caps", "--rooms", "2", "--frames", "4", "--size", "32x24",
            "--gaussians", "2000", "--no-progress", "--seed", "3"]
    assert main([str(a) for a in argv + ["--out", tmp_path / "a"]]) == 0
    assert main([str(a) for a in argv + ["--out", tmp_path / "b"]]) == 0
    a, b = snapshot(tmp_path / "a"), snapshot(tmp_path / "b")
    assert a == b and sorted(p.split("/")[0] for p in a if p.endswith(".ply")) == ["column_statue_01", "column_tabletop_00"]
    found = discover_teachers(tmp_path / "a")
    assert not found.rejected and {t.subset for t in found.teachers} == {"captures-in-rooms"}
    desk = next(t for t in found.teachers if "tabletop" in t.scene_id)
    assert desk.baseline == 0.063 and desk.sh_degree == 1 and desk.num_frames == 4
    assert main(["build", "--teachers", str(tmp_path / "a"), "--out", str(tmp_path / "ds"), "--min-psnr", "none",
                 "--val-scenes", "0", "--targets", "1", "--device", "cpu", "--no-progress", "--workers", "1"]) == 0
    metas = [json.loads(members["json"]) for shard in sorted((tmp_path / "ds" / "train").glob("shard-*.tar"))
             for _, members in shards.iter_shard(shard)]
    assert len(metas) == 8
    assert {(m["scene"].split("_")[1], m["baseline"]) for m in metas} == {("tabletop", 0.063), ("statue", 0.1)}
    assert capture.exists()


BAD = [  # (name, writer of tmp/caps/<file>, part of the one-line refusal)
    ("nan", lambda d: write_nan_ply(d / "nan.ply"), "nan.ply: 1 of 8 Gaussians have bad rows: 1 with non-finite"),
    ("all_faint", lambda d: write_capture(d / "faint.ply", opacities=np.full(BODY + 45, 0.01, np.float32)),
     "faint.ply: no Gaussian left after dropping floaters"),
    ("one_point", lambda d: write_capture(d / "point.ply", means=np.zeros((BODY + 45, 3), np.float32)),
     "point.ply: object extent 0.0 is not a finite size > 0"),
    ("not_a_scene", lambda d: (d / "junk.ply").write_bytes(b"hello"), "junk.ply"),
    ("empty_folder", lambda d: (d / "notes.txt").write_text("x"), "--captures"),
]


def write_nan_ply(path: Path) -> Path:
    rng = np.random.default_rng(0)
    names = inria_names(0)
    raw = {n: rng.normal(size=8).astype(np.float32).astype(np.float64) for n in names}
    raw["x"][3] = np.nan
    return write_ply(path, inria_props(raw, names))


@pytest.mark.parametrize("name,make,message", BAD, ids=[b[0] for b in BAD])
def test_bad_captures_are_refused_in_one_line_and_nothing_is_written(tmp_path, capsys, name, make, message):
    caps = tmp_path / "caps"
    caps.mkdir()
    make(caps)
    before = snapshot(tmp_path)
    rc, err = refusal(main, ["compose-teachers", "--captures", caps, "--out", tmp_path / "out", "--no-progress"], capsys)
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert snapshot(tmp_path) == before and not (tmp_path / "out").exists()


def test_bad_outputs_and_flags_are_refused(tmp_path, capsys):
    caps = tmp_path / "caps"
    caps.mkdir()
    write_capture(caps / "column.ply")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "keep.txt").write_text("mine")
    for argv, message in [
        (["--out", tmp_path / "mine"], "--out"),                                   # a folder we did not write
        (["--out", caps / "teachers"], "inside --captures"),                        # inside the inputs
        (["--out", tmp_path / "o", "--scales", "giant"], "--scales"),
        (["--out", tmp_path / "o", "--up", "up"], "--up"),
    ]:
        before = snapshot(tmp_path)
        rc, err = refusal(main, ["compose-teachers", "--captures", caps, *argv, "--no-progress"], capsys)
        assert rc == 2 and message in err, err
        assert snapshot(tmp_path) == before
    (tmp_path / "other").mkdir()
    write_capture(tmp_path / "other" / "column.spz.ply")
    rc, err = refusal(main, ["compose-teachers", "--captures", caps / "column.ply", tmp_path / "other" / "column.spz.ply",
                             "--out", tmp_path / "o", "--no-progress"], capsys)
    assert rc == 2 and "two captures are named 'column'" in err and not (tmp_path / "o").exists()


@pytest.mark.real_data
def test_real_guitar_composed_upright_at_desk_scale(guitar_ply):
    """The guitar (y down, about 4.2 units) becomes a 0.15-0.6 m object on a table, its long axis vertical."""
    capture = read_capture(guitar_ply)
    c = compose_teacher(capture, FAMILIES["tabletop"], np.random.default_rng(0), 8, (64, 48), 2000)
    obj = c.scene.means[c.object_rows].astype(np.float64)
    w = c.scene.opacities[c.object_rows].astype(np.float64)
    sides = [weighted_quantile(obj[:, a], w, 0.99) - weighted_quantile(obj[:, a], w, 0.01) for a in range(3)]
    assert max(sides) == pytest.approx(c.size, rel=1e-5) and 0.15 <= c.size <= 0.6
    assert int(np.argmax(sides)) == 2                                           # the guitar stands: tallest along z
    assert len(capture.scene) > 0.5 * len(load_ply(guitar_ply))


@pytest.mark.real_data
def test_the_shared_statues_stand_upright_once_their_format_is_read(shared_data):
    """The SOG statues (y down, PROVENANCE.md) measured: floaters dropped, a finite size, and their tallest side
    along z after the upright turn. Skips while ``load_scene`` has no SOG reader (branch formats-read)."""
    statues = sorted((shared_data / "captures").glob("statue-*/*.sog"))
    if not statues:
        pytest.skip(f"no statue captures under {shared_data / 'captures'}")
    try:
        load_scene(statues[0])
    except PlyError as e:
        pytest.skip(f"scene_files.load_scene reads no SOG yet: {e}")
    captures = [read_capture(p) for p in statues]
    for c in captures:
        sides = c.hi - c.lo
        assert len(c.scene) > 0.5 * (len(c.scene) + c.dropped) and np.isfinite(c.size) and c.size > 0
        assert int(np.argmax(sides)) == 2, f"{c.path.name}: bounds {sides.tolist()} are not tallest along z"
