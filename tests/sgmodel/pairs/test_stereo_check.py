"""The stereo check before the model: a rectified pair passes with its figures measured against the rendered
ground truth; a swapped, a vertically shifted, a rotated, an unrectified and a textureless pair warn (and
``--strict`` stops with exit 2, writing nothing)."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest

from scenesplat_stereo.shards.encode import encode_png, to_uint8
from scripts.inputs.rig_pair import BASELINE, H, W, render
from sgmodel.cli import main as sgmodel_main
from sgmodel.pairs.stereo_check import DY_MEDIAN_MAX, StereoCheckError, matches, measure, run_check
from tests.support.model_helpers import predict_status as _predict

K = np.array([[250.0, 0, W / 2], [0, 250.0, H / 2], [0, 0, 1]])


@pytest.fixture(scope="module")
def ideal_pair(raw_rig):
    """A rectified pair rendered directly (left [H,W,3] uint8, right, left z-depth [H,W] metres)."""
    truth = raw_rig("radtan").rig
    right = truth.c2w_rect.copy()
    right[:3, 3] += BASELINE * right[:3, 0]
    rgb, depth = render(raw_rig("radtan").scene, [truth.c2w_rect, right], [K, K], W, H)
    return to_uint8(rgb[0]), to_uint8(rgb[1]), depth[0]


def shifted(image: np.ndarray, dx: float = 0.0, dy: float = 0.0, degrees: float = 0.0, scale: float = 1.0):
    """The image moved by (dx, dy) pixels and turned by ``degrees`` about its centre (content moves)."""
    h, w = image.shape[:2]
    M = cv2.getRotationMatrix2D((w / 2 - 0.5, h / 2 - 0.5), degrees, 1.0)
    M[:, 2] += (dx, dy)
    out = cv2.warpAffine(image, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return cv2.resize(out, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC) if scale != 1 else out


def test_a_rectified_pair_passes_and_its_disparity_matches_the_rendered_depth(ideal_pair):
    left, right, depth = ideal_pair
    check = measure(left, right)
    print(check.summary())
    assert check.warnings == () and check.matches >= 100
    assert check.dy_median < 0.2 and check.dy_p95 < 1.0 and check.negative_fraction == 0
    p1, p2 = matches(left, right)                       # OpenCV pixel centres: index = round(x)
    z = depth[np.rint(p1[:, 1]).astype(int), np.rint(p1[:, 0]).astype(int)]
    truth = K[0, 0] * BASELINE / z[z > 0]
    assert np.median(np.abs((p1[:, 0] - p2[:, 0])[z > 0] - truth)) < 0.3
    assert abs(check.disparity[1] - np.median(truth)) < 0.5


def test_swapped_pair_warns_and_strict_stops(ideal_pair):
    left, right, _ = ideal_pair
    check = measure(right, left)
    assert check.negative_fraction > 0.9 and len(check.warnings) == 1
    assert re.search(r"^\d+% of \d+ matches have negative disparity \(median -\d+\.\d px\): the left and right "
                     r"images are probably swapped", check.warnings[0])
    lines = []
    run_check(right, left, strict=False, log=lines.append, warn=lines.append)
    assert lines[0].endswith(": WARNING") and lines[1].startswith("warning: stereo check: ") and len(lines) == 2
    with pytest.raises(StereoCheckError, match=r"stereo check: .* swapped .*\(--strict\)"):
        run_check(right, left, strict=True, log=lines.append)


@pytest.mark.parametrize("dy", [3.0, -2.0])
def test_vertically_shifted_pair_warns_with_the_shift(ideal_pair, dy):
    left, right, _ = ideal_pair
    check = measure(left, shifted(right, dy=dy))
    assert check.dy_shift == pytest.approx(dy, abs=0.15) and len(check.warnings) == 1
    assert f"nearly the same everywhere (the right image {dy:+.1f} px lower)" in check.warnings[0]
    assert "cropped or shifted differently" in check.warnings[0]


def test_sub_pixel_shift_passes_and_the_figures_scale_to_the_input_pixels(ideal_pair):
    left, right, _ = ideal_pair
    assert measure(left, shifted(right, dy=0.5)).warnings == ()
    # 5x larger images are measured at MAX_SIDE and reported in their own pixels: a 3 px shift becomes 15.
    big = measure(shifted(left, scale=5), shifted(right, dy=3.0, scale=5))
    assert big.dy_shift == pytest.approx(15.0, abs=0.5) and big.disparity[1] > 5 * 8


@pytest.mark.parametrize("rectified_here,cause", [(False, "the pair is not rectified, or was rectified with another"),
                                                  (True, "the calibration does not fit these images")])
def test_rotated_pair_warns_with_the_likely_cause(ideal_pair, rectified_here, cause):
    left, right, _ = ideal_pair
    check = measure(left, shifted(right, degrees=1.5), rectified_here=rectified_here)
    assert check.dy_median > DY_MEDIAN_MAX and len(check.warnings) == 1 and cause in check.warnings[0]
    assert "varying across the image" in check.warnings[0]


def test_textureless_and_tiny_pairs_cannot_be_verified():
    for flat in (np.full((H, W, 3), 128, np.uint8), np.zeros((16, 16, 3), np.float32)):
        check = measure(flat, flat)
        assert check.matches == 0 and "the check cannot tell" in check.warnings[0]
        assert "too few to measure" in check.summary()
        assert json.loads(json.dumps(check.to_json(), allow_nan=False))["dy_median_px"] is None


def test_middlebury_doffs_makes_image_disparities_valid(ideal_pair):
    left, right, _ = ideal_pair
    moved = shifted(right, dx=30.0)                      # image disparity d - 30 < 0, true disparity d
    assert "swapped" in measure(left, moved).warnings[0]
    assert measure(left, moved, doffs=30.0).warnings == ()


def test_predict_warns_reports_and_strict_exits_2(ideal_pair, raw_rig, tmp_path, capsys):
    left, right, _ = ideal_pair
    for name, image in (("l.png", left), ("r.png", right)):
        (tmp_path / name).write_bytes(encode_png(image))
    calib = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
    common = ["--intrinsics", calib, "--baseline", BASELINE, "--method", "forward-splat", "--encoder", "sgbm",
              "--device", "cpu", "--resolution", H]
    out = tmp_path / "out"
    assert _predict(["--left", tmp_path / "r.png", "--right", tmp_path / "l.png", *common, "--out", out]) == 0
    captured = capsys.readouterr()
    assert "swapped" in captured.err and captured.err.startswith("sgmodel predict: warning: stereo check: ")
    assert len(captured.err.strip().splitlines()) == 1
    summary = captured.out.strip().splitlines()[-2]
    assert summary.startswith("stereo check: ") and summary.endswith(": WARNING")
    strict_out = tmp_path / "strict"
    assert _predict(["--left", tmp_path / "r.png", "--right", tmp_path / "l.png", *common, "--out", strict_out,
                     "--strict"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sgmodel predict: error: stereo check: ") and "(--strict)" in err and not strict_out.exists()
    assert len(err.strip().splitlines()) == 1
    # A raw (unrectified) pair given with intrinsics: the check says it is not rectified and points to --rig.
    r = raw_rig("radtan")
    assert _predict(["--left", r.folder / "left.png", "--right", r.folder / "right.png", *common, "--out", out,
                     "--strict"]) == 2
    err = capsys.readouterr().err
    assert "the pair is not rectified (one camera tilted): give the raw calibration with --rig" in err


def test_rectify_strict_refuses_a_swapped_rig_pair(raw_rig, tmp_path, capsys):
    r = raw_rig("radtan")
    out = tmp_path / "rect"
    assert sgmodel_main(["rectify", "--left", str(r.folder / "right.png"), "--right", str(r.folder / "left.png"),
                         "--rig", str(r.folder / "opencv.yml"), "--out", str(out), "--strict"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sgmodel rectify: error: stereo check: ") and not out.exists()
    assert "the calibration does not fit these images" in err


def test_mismatches_far_off_the_rows_are_dropped_but_a_real_spread_is_kept(monkeypatch):
    """RANSAC can keep a few mismatches on repeated texture (one demo view kept two with dy of 120 and 142 px
    among 32 matches): the robust cut drops them; a rotated pair's wide spread of dy stays."""
    rng = np.random.default_rng(0)
    p1 = rng.uniform([0, 0], [W, H], (60, 2))
    p2 = p1 - [12.0, 0.0] + rng.normal(0, 0.1, (60, 2))
    p2[:3, 1] += [120.0, -90.0, 140.0]
    monkeypatch.setattr("sgmodel.pairs.stereo_check.matches", lambda left, right, max_side: (p1, p2))
    check = measure(None, None)
    assert check.matches == 57 and check.warnings == () and check.dy_p95 < 0.5
    p2[:, 1] = p1[:, 1] + np.tan(np.radians(3)) * (p1[:, 0] - W / 2)     # a 3 degree roll: |dy| up to 8 px
    check = measure(None, None)
    assert check.matches == 60 and check.dy_p95 > 6 and "varying across the image" in check.warnings[0]
