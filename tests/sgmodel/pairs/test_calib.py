"""Calibration files of user stereo pairs: FoundationStereo K.txt, Middlebury 2014 calib.txt, flags."""

from __future__ import annotations

import numpy as np
import pytest

from sgmodel.pairs.calib import CalibError, calib_from_flags, read_calib

MIDDLEBURY = """cam0=[3997.684 0 1176.728; 0 3997.684 1011.728; 0 0 1]
cam1=[3997.684 0 1307.839; 0 3997.684 1011.728; 0 0 1]
doffs=131.111
baseline=193.001
width=2964
height=1988
ndisp=280
isint=0
vmin=31
vmax=257
dyavg=0.918
dymax=1.516
"""


def write(tmp_path, text, name="calib.txt"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_foundation_stereo_format(tmp_path):
    c = read_calib(write(tmp_path, "754.6680 0.0 489.3794 0.0 754.6680 265.1635 0.0 0.0 1.0\n0.063\n", "K.txt"))
    np.testing.assert_array_equal(c.K, [[754.668, 0, 489.3794], [0, 754.668, 265.1635], [0, 0, 1]])
    assert c.baseline == 0.063 and c.doffs == 0.0 and c.size is None


def test_middlebury_format_baseline_in_millimetres_and_doffs(tmp_path):
    c = read_calib(write(tmp_path, MIDDLEBURY))
    np.testing.assert_array_equal(c.K, [[3997.684, 0, 1176.728], [0, 3997.684, 1011.728], [0, 0, 1]])
    assert c.baseline == pytest.approx(0.193001, rel=1e-12) and c.doffs == 131.111 and c.size == (2964, 1988)
    c.check_size(2964, 1988, "im0.png")
    with pytest.raises(CalibError, match=r"calib.txt: width=2964, height=1988 do not match im0.png \(1482x994\)"):
        c.check_size(1482, 994, "im0.png")
    half = c.scaled(0.5, 0.5)
    assert half.K[0, 0] == pytest.approx(1998.842) and half.K[1, 2] == pytest.approx(505.864)
    assert half.doffs == pytest.approx(65.5555) and half.baseline == c.baseline and half.size is None
    # without doffs=, it is cx1 - cx0
    c = read_calib(write(tmp_path, MIDDLEBURY.replace("doffs=131.111\n", "")))
    assert c.doffs == pytest.approx(1307.839 - 1176.728)


def test_flags():
    c = calib_from_flags("500,510,320.5,240", "0.12")
    np.testing.assert_array_equal(c.K, [[500, 0, 320.5], [0, 510, 240], [0, 0, 1]])
    assert c.baseline == 0.12


BAD_FILES = [
    ("754 0 489 0 754 265 0 0\n0.063\n", r"line 1 \(K\) must hold 9 numbers, got 8"),
    ("754 0 489 0 754 265 0 0 1\n", r"2 lines .* got 1"),
    ("754 0 489 0 754 265 0 0 1\n0.06 0.07\n", r"line 2 \(baseline\) must hold 1 number"),
    ("754 0 489 0 754 265 0 0 1\nabc\n", r"line 2 \(baseline\): 'abc' is not a number"),
    ("754 0 489 0 754 265 0 0 1\n0\n", r"line 2 \(baseline\): baseline must be positive"),
    ("-754 0 489 0 754 265 0 0 1\n0.06\n", r"line 1 \(K\): focal lengths must be positive"),
    ("754 0 489 0 754 265 0 0 2\n0.06\n", r"line 1 \(K\): K must be"),
    ("754 0 489 0 754 265 0 0 1\nnan\n", r"not a finite number"),
    ("hello world\n", r"unknown calibration format"),
    ("", r"unknown calibration format"),
    (MIDDLEBURY.replace("baseline=193.001", "baseline=-5"), r"line 4 \(baseline\): baseline must be positive"),
    (MIDDLEBURY.replace("baseline=193.001\n", ""), r"without baseline="),
    (MIDDLEBURY.replace("cam0=[3997.684 0", "cam0=[0 0"), r"line 1 \(cam0\): focal lengths must be positive"),
    (MIDDLEBURY.replace("; 0 0 1]\ncam1", "]\ncam1"), r"line 1 \(cam0\): expected a 3x3 matrix"),
    (MIDDLEBURY.replace("width=2964", "width=29x4"), r"line 5 \(width\): '29x4' is not a number"),
    (MIDDLEBURY.replace("width=2964", "width=0"), r"line 5 \(width\): width must be a positive integer"),
    (MIDDLEBURY.replace("height=1988\n", ""), r"width= and height= must be given together"),
    (MIDDLEBURY + "focal=3\n", r"line 13: expected one of"),
    (MIDDLEBURY + "ndisp=3\n", r"line 13 \(ndisp\): ndisp given twice"),
    (MIDDLEBURY.replace("cam1=[3997.684 0 1307.839; 0 3997.684", "cam1=[3997.684 0 1307.839; 0 3000"),
     r"line 2 \(cam1\): a rectified pair has the same fx, fy and cy"),
]


@pytest.mark.parametrize("text,message", BAD_FILES)
def test_bad_files_name_the_file_and_field(tmp_path, text, message):
    p = write(tmp_path, text)
    with pytest.raises(CalibError, match=message) as e:
        read_calib(p)
    assert str(p) in str(e.value)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(CalibError, match="calibration file not found"):
        read_calib(tmp_path / "nope.txt")
    p = tmp_path / "bin.txt"
    p.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(CalibError, match="cannot read"):
        read_calib(p)


@pytest.mark.parametrize("intrinsics,baseline,message", [
    ("500,510,320", "0.1", r"--intrinsics: expected 4"),
    ("500,x,320,240", "0.1", r"--intrinsics: 'x' is not a number"),
    ("0,510,320,240", "0.1", r"--intrinsics: focal lengths must be positive"),
    ("500,510,320,240", "-0.1", r"--baseline: baseline must be positive"),
    ("500,510,320,240", "ten", r"--baseline: 'ten' is not a number"),
])
def test_bad_flags(intrinsics, baseline, message):
    with pytest.raises(CalibError, match=message):
        calib_from_flags(intrinsics, baseline)
