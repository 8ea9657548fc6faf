"""pipelines/irs.py and irs_pose_recovery.py: metric scale, filters and outputs of IRS pose recovery, on a
synthetic IRS-like variant with known poses (tests/support/irs_synthetic.py) and on broken variants."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from pipelines import irs, irs_pose_recovery  # noqa: E402
from scenesplat_stereo.captured.colmap import Observations, Recovery, RecoveryOptions  # noqa: E402
from tests.support.irs_synthetic import align, cached_variant, write_disparity_exr  # noqa: E402

FAST = RecoveryOptions(max_num_features=1024, num_threads=1)  # one thread: COLMAP runs deterministically
FILTERS = irs.Filters(min_registered=20)  # the synthetic variant has 32 frames, not >= 150


@pytest.fixture(scope="module")
def variant(tmp_path_factory):
    return cached_variant(tmp_path_factory.getbasetemp())


def _png(path: Path, rgb: np.ndarray) -> None:
    import OpenImageIO as oiio

    assert oiio.ImageBuf(np.ascontiguousarray(rgb)).write(str(path))


def _copy_frames(src: Path, dst: Path, frames: range) -> Path:
    dst.mkdir(parents=True)
    for n in frames:
        for name in (f"l_{n}.png", f"r_{n}.png", f"d_{n}.exr"):
            shutil.copy(src / name, dst / name)
    return dst


def _broken_root(src: Path, root: Path) -> dict[str, Path]:
    """Variants that must be reported, not crash (folder name -> path)."""
    b = root / "Broken"
    made = {"partial": _copy_frames(src, b / "Partial", range(1, 11))}
    for name in ("d_3.exr", "d_7.exr", "r_5.png"):
        (made["partial"] / name).unlink()
    made["zero"] = _copy_frames(src, b / "ZeroDisparity", range(1, 9))
    made["negative"] = _copy_frames(src, b / "NegativeDisparity", range(1, 9))
    for n in range(1, 9):
        write_disparity_exr(made["zero"] / f"d_{n}.exr", np.zeros((135, 240)))
        d = -np.ones((135, 240))
        d[:5] = np.nan
        write_disparity_exr(made["negative"] / f"d_{n}.exr", d)
    made["few"] = _copy_frames(src, b / "TooFew", range(1, 2))
    made["blank"] = b / "Blank"
    made["blank"].mkdir()
    made["size"] = b / "WrongSize"
    made["size"].mkdir()
    for n in range(1, 7):
        _png(made["blank"] / f"l_{n}.png", np.full((135, 240, 3), 90, np.uint8))
        _png(made["blank"] / f"r_{n}.png", np.full((135, 240, 3), 90, np.uint8))
        write_disparity_exr(made["blank"] / f"d_{n}.exr", np.full((135, 240), 20.0))
        _png(made["size"] / f"l_{n}.png", np.zeros((100, 200, 3), np.uint8))
        _png(made["size"] / f"r_{n}.png", np.zeros((100, 200, 3), np.uint8))
        write_disparity_exr(made["size"] / f"d_{n}.exr", np.full((100, 200), 20.0))
    made["unreadable"] = _copy_frames(src, b / "Unreadable", range(1, 4))
    (made["unreadable"] / "l_2.png").write_bytes(b"not a png")
    return made


# ------------------------------------------------------------------------------------- pure functions
def test_variant_names_and_scan(tmp_path):
    root = tmp_path / "IRS"
    shop = root / "Store" / "Shop__1"
    shop.mkdir(parents=True)
    for n in (1, 2, 10):
        (shop / f"l_{n}.png").touch()
        (shop / f"r_{n}.png").touch()
    (shop / "d_1.exr").touch()
    (shop / "d_10.exr").touch()
    (root / "Store" / "notes.txt").touch()
    assert irs.find_variants(root) == [shop]
    assert irs.variant_name(root, shop) == "Store-Shop_1"  # never '__', the shard key separator
    assert irs.variant_name(shop, shop) == "Shop__1".replace("__", "_")
    v = irs.scan_variant(root, shop)
    assert [f.n for f in v.frames] == [1, 10]  # numeric order, frame 2 has no disparity
    assert dict(v.problems) == {"missing disparity": 1}
    with pytest.raises(FileNotFoundError, match="not a folder"):
        irs.find_variants(tmp_path / "nowhere")
    (root / "Store-Shop_1").mkdir()
    (root / "Store-Shop_1" / "l_1.png").touch()
    with pytest.raises(ValueError, match="same output name"):
        irs.run_dataset(root, irs.VariantConfig(out=tmp_path / "out"), progress=False)


def test_read_disparity_and_depth(tmp_path):
    import OpenImageIO as oiio

    rgb = np.stack([np.full((4, 6), 12.0), np.full((4, 6), 99.0), np.full((4, 6), 99.0)], axis=-1)
    assert oiio.ImageBuf(rgb.astype(np.float32)).write(str(tmp_path / "d_1.exr"), oiio.FLOAT)
    d = irs.read_disparity(tmp_path / "d_1.exr")
    assert d.shape == (4, 6) and d.dtype == np.float32 and (d == 12.0).all()  # first channel
    z = irs.depth_from_disparity(np.array([48.0, 24.0, 0.0, -3.0, np.nan, np.inf]))
    np.testing.assert_array_equal(z[:2], [1.0, 2.0])  # z = 48 / d metres
    assert np.isnan(z[2:]).all()
    (tmp_path / "bad.exr").write_bytes(b"junk")
    with pytest.raises(ValueError, match=r"bad\.exr"):
        irs.read_disparity(tmp_path / "bad.exr")


def test_metric_scale_median_iqr_and_invalid(tmp_path):
    # Two 10x20 images; true depth z = 48 / d; reconstructed depth = z / s_i per observation.
    rng = np.random.default_rng(3)
    frames, observations, expected = [], [], []
    for k in range(2):
        d = rng.uniform(5, 40, (10, 20))
        d[0, 0], d[0, 1], d[0, 2] = 0.0, -2.0, np.nan  # invalid pixels
        path = tmp_path / f"d_{k}.exr"
        write_disparity_exr(path, d)
        d = irs.read_disparity(path).astype(np.float64)  # what the pipeline sees (float32)
        px = np.array([[0, 0], [1, 0], [2, 0]] + [[x, y] for y in range(1, 10) for x in range(0, 20, 3)])
        xy = px + rng.uniform(0, 1, px.shape)  # anywhere inside the pixel: floor() picks it
        scale = rng.uniform(1.5, 2.5, len(px))
        z_rec = 48.0 / np.where(d[px[:, 1], px[:, 0]] > 0, d[px[:, 1], px[:, 0]], 1.0) / scale
        z_rec[-1] = -1.0  # a point behind the camera: invalid
        expected.append(scale[3:-1])
        observations.append(Observations(xy, z_rec, np.arange(len(px))))
        frames.append(irs.IrsFrame(k, tmp_path / "l.png", tmp_path / "r.png", path))
    rec = Recovery(2, [0, 1], np.tile(np.eye(4), (2, 1, 1)), observations, 0.1, 10, 1, "exhaustive")
    est = irs.metric_scale(rec, frames)
    ratios = np.concatenate(expected)
    q25, q50, q75 = np.percentile(ratios, [25, 50, 75])
    assert est.used == len(ratios) and est.invalid == 2 * 4
    assert est.median == pytest.approx(q50, rel=1e-9) and est.iqr == pytest.approx(q75 - q25, rel=1e-9)


def test_filter_thresholds_are_inclusive():
    f = irs.Filters()
    assert (f.min_registered, f.max_reprojection_error, f.max_scale_iqr_fraction) == (150, 1.5, 0.25)
    ok = irs.ScaleEstimate(median=2.0, iqr=0.5, used=100, invalid=0)  # IQR exactly 25% of the median
    assert irs.filter_reasons(150, 1.5, ok, f) == []
    assert irs.filter_reasons(149, 1.5, ok, f) == ["registered frames 149 < 150"]
    assert irs.filter_reasons(150, 1.5001, ok, f)[0].startswith("mean reprojection error 1.500 px > 1.5")
    wide = irs.ScaleEstimate(median=2.0, iqr=0.5001, used=100, invalid=0)
    assert irs.filter_reasons(150, 1.0, wide, f) == ["scale IQR 25.0% of median > 25%"]
    none = irs.ScaleEstimate(float("nan"), float("nan"), 0, 7)
    assert irs.filter_reasons(150, 1.0, none, f) == ["no metric scale (no sparse point with a valid disparity)"]
    assert irs.filter_reasons(0, float("nan"), None, f) == [
        "registered frames 0 < 150", "no mean reprojection error (nothing registered)",
        "no metric scale (no sparse point with a valid disparity)"]


def test_stereo_poses_right_is_left_times_baseline_translation():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    c2w = np.eye(4)
    c2w[:3, :3] = q * np.sign(np.linalg.det(q))
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    left, right = irs.stereo_poses(c2w[None], scale=0.5)
    trans = np.eye(4)
    trans[0, 3] = 0.1
    np.testing.assert_allclose(left[0][:3, 3], [0.5, 1.0, 1.5])
    np.testing.assert_allclose(left[0][:3, :3], c2w[:3, :3])
    np.testing.assert_allclose(right[0], left[0] @ trans, atol=1e-12)


# --------------------------------------------------------------------------------- end to end (COLMAP)
@pytest.mark.slow
def test_dataset_recovery_accuracy_filters_and_broken_inputs(variant, tmp_path, monkeypatch):
    root = tmp_path / "IRS"
    (root / "Home").mkdir(parents=True)
    os.symlink(variant.folder, root / "Home" / "Synth")
    broken = _broken_root(variant.folder, root)
    out = tmp_path / "poses"
    cfg = irs.VariantConfig(out=out, camera=variant.camera, filters=FILTERS, options=FAST)
    reports = {r["variant"]: r for r in irs.run_dataset(root, cfg, workers=1, progress=False)}
    assert sorted(reports) == sorted(["Home-Synth"] + [f"Broken-{p.name}" for p in broken.values()])

    # The clean variant: all frames registered, kept, metric poses accurate.
    good = reports["Home-Synth"]
    assert good["kept"] and good["reasons"] == [] and good["registered"] == 32 and good["frames_left_out"] == {}
    assert good["camera_params"] == [120.0, 120.0, 120.0, 67.5]
    assert good["scale_iqr"] <= 0.25 * good["scale_median"] and good["mean_reprojection_error"] <= 1.5
    poses = json.loads((out / "Home-Synth" / "poses.json").read_text())
    assert [f["frame"] for f in poses["frames"]] == list(range(1, 33))
    assert poses["K"] == [[120.0, 0.0, 120.0], [0.0, 120.0, 67.5], [0.0, 0.0, 1.0]] and poses["baseline"] == 0.1
    left = np.array([f["c2w_left"] for f in poses["frames"]])
    right = np.array([f["c2w_right"] for f in poses["frames"]])
    a = align(left, variant.c2w, scale=1.0)  # poses are already in metres
    assert abs(a.scale - 1.0) <= 0.02, a  # recovered metric scale within 2% of the truth
    assert a.max_centre_error <= 0.01 * variant.trajectory_length, a
    assert a.max_rotation_error_deg <= 0.5, a
    trans = np.eye(4)
    trans[0, 3] = 0.1
    np.testing.assert_allclose(right, left @ trans, atol=1e-9)
    assert not (out / "Home-Synth" / "colmap").exists()  # work files removed

    # Broken variants: reported with counts and reasons, never an exception.
    def r(key: str) -> dict:
        return reports[f"Broken-{broken[key].name}"]

    assert r("partial")["frames_left_out"] == {"missing disparity": 2, "missing right image": 1}
    assert r("partial")["frames_used"] == 7 and r("partial")["reasons"] == ["registered frames 7 < 20"]
    for key in ("zero", "negative"):
        assert r(key)["registered"] >= 2 and r(key)["scale_observations"] == 0
        assert r(key)["invalid_disparity_observations"] > 0
        assert "no metric scale (no sparse point with a valid disparity)" in r(key)["reasons"]
        assert not (out / f"Broken-{broken[key].name}" / "poses.json").exists()
    assert r("few")["reasons"] == ["too few usable frames (1)"]
    assert r("blank")["registered"] == 0 and r("blank")["reasons"] == [
        "registered frames 0 < 20", "no mean reprojection error (nothing registered)",
        "no metric scale (no sparse point with a valid disparity)"]
    assert r("size")["frames_left_out"] == {"wrong image size": 6}
    assert r("size")["reasons"] == ["too few usable frames (0)"]
    assert r("unreadable")["frames_left_out"] == {"unreadable file": 1} and r("unreadable")["frames_used"] == 2
    for rep in reports.values():
        assert (out / rep["variant"] / "report.json").is_file()
        assert not any(reason.startswith(("error", "worker")) for reason in rep["reasons"]), rep
    summary = json.loads((out / "summary.json").read_text())
    assert summary["variants"] == len(reports) and summary["kept"] == 1

    # Resumable: a second run reuses every report.json and recovers nothing.
    def fail(*args, **kwargs):
        raise AssertionError("a finished variant was recovered again")

    monkeypatch.setattr(irs, "recover_variant", fail)
    again = irs.run_dataset(root, cfg, workers=1, progress=False)
    assert [x["variant"] for x in again] == sorted(reports)
    assert again[sorted(reports).index("Home-Synth")]["registered"] == 32


@pytest.mark.slow
def test_command_parallel_workers_and_summary(variant, tmp_path, capsys):
    root = tmp_path / "IRS"
    _copy_frames(variant.folder, root / "A", range(1, 9))
    _copy_frames(variant.folder, root / "B", range(1, 2))
    (root / "C").mkdir()
    _png(root / "C" / "l_1.png", np.zeros((135, 240, 3), np.uint8))
    out = tmp_path / "out"
    args = [str(root), "--out", str(out), "--workers", "2", "--image-size", "240x135", "--min-registered", "5",
            "--max-features", "1024", "--no-progress"]
    assert irs_pose_recovery.main(args) == 0
    table = capsys.readouterr().out
    lines = table.splitlines()
    assert lines[0].split()[:3] == ["variant", "frames", "reg"] and "total 3" in lines[-1]
    row = {line.split()[0]: line for line in lines[2:-1]}
    assert row["A"].rstrip().endswith("kept") and "too few usable frames (1)" in row["B"]
    assert "too few usable frames (0)" in row["C"]
    rep_c = json.loads((out / "C" / "report.json").read_text())
    assert rep_c["frames_left_out"] == {"missing right image": 1}
    a = json.loads((out / "A" / "report.json").read_text())
    assert a["kept"] and a["registered"] == 8 and a["thresholds"]["min_registered"] == 5
    stamp = (out / "A" / "report.json").stat().st_mtime_ns
    assert irs_pose_recovery.main(args) == 0  # resumed: nothing redone
    assert (out / "A" / "report.json").stat().st_mtime_ns == stamp
    assert capsys.readouterr().out == table
    assert irs_pose_recovery.main([str(tmp_path / "missing"), "--out", str(out)]) == 2
    assert irs_pose_recovery.main(args + ["--vocab-tree", str(tmp_path / "no.bin")]) == 2
