"""Raw stereo-rig calibration files (``--rig``): OpenCV FileStorage YAML/XML and Kalibr camchain.yaml, read
against the ground truth that wrote them, and every malformed file refused in one line naming file and field."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from scripts.inputs.rig_pair import H, W, kalibr_yaml, make_rig, opencv_yaml
from sgmodel.pairs.rig import FISHEYE, PINHOLE, RigError, read_rig


def storage(values: dict, ext: str = ".yml") -> bytes:
    """An OpenCV FileStorage file (written by cv2.FileStorage) holding ``values``."""
    fs = cv2.FileStorage(ext, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    for name, value in values.items():
        fs.write(name, value)
    return fs.releaseAndGetString().encode()


def opencv_fields(model: str = "radtan") -> dict:
    rig = make_rig(model)
    return {"K1": rig.K0, "D1": rig.D0[None], "K2": rig.K1, "D2": rig.D1[None], "R": rig.R, "T": rig.T[:, None],
            "imageSize": (W, H), "distortion_model": "fisheye" if model == "equidistant" else "radtan"}


def kalibr_fields(model: str = "radtan") -> dict:
    return yaml.safe_load(kalibr_yaml(make_rig(model)))


def write(tmp_path, data: bytes | str, name: str = "rig.yml"):
    p = tmp_path / name
    p.write_bytes(data.encode() if isinstance(data, str) else data)
    return p


def assert_matches_truth(rig, model: str) -> None:
    truth = make_rig(model)
    np.testing.assert_allclose(rig.K1, truth.K0, rtol=1e-15)
    np.testing.assert_allclose(rig.K2, truth.K1, rtol=1e-15)
    n = 5 if model == "radtan" and rig.D1.size == 5 else 4
    np.testing.assert_allclose(rig.D1, truth.D0[:n], rtol=1e-15)
    np.testing.assert_allclose(rig.D2, truth.D1[:n], rtol=1e-15)
    np.testing.assert_allclose(rig.R, truth.R, atol=1e-15)
    np.testing.assert_allclose(rig.T, truth.T, atol=1e-16)
    assert rig.baseline == pytest.approx(0.1, rel=1e-14)
    assert rig.model == (FISHEYE if model == "equidistant" else PINHOLE) and rig.size == (W, H)


@pytest.mark.parametrize("model", ["radtan", "equidistant"])
def test_opencv_yaml_xml_and_kalibr_read_the_truth(tmp_path, model):
    assert_matches_truth(read_rig(write(tmp_path, storage(opencv_fields(model)))), model)
    assert_matches_truth(read_rig(write(tmp_path, storage(opencv_fields(model), ".xml"), "rig.xml")), model)
    assert_matches_truth(read_rig(write(tmp_path, kalibr_yaml(make_rig(model)), "camchain.yaml")), model)


def test_opencv_sample_two_files_m1_spelling_and_units(tmp_path):
    """samples/cpp/stereo_calib.cpp writes intrinsics.yml (M1 D1 M2 D2) and extrinsics.yml (R T R1 ...)."""
    rig = make_rig()
    intr = write(tmp_path, opencv_yaml(rig, ("M1", "D1", "M2", "D2")), "intrinsics.yml")
    extr = write(tmp_path, storage({"R": rig.R, "T": rig.T[:, None] * 1000, "R1": np.eye(3), "P1": np.eye(3, 4),
                                    "Q": np.eye(4)}), "extrinsics.yml")
    r = read_rig([intr, extr], units="mm")
    np.testing.assert_allclose(r.T, rig.T, rtol=1e-15)
    assert r.size is None and r.model == PINHOLE and str(intr) in r.source and str(extr) in r.source
    assert read_rig([str(intr), str(extr)], units="cm").baseline == pytest.approx(1.0)


def test_hand_written_yaml_rodrigues_and_no_distortion(tmp_path):
    rig = make_rig()
    rvec = cv2.Rodrigues(rig.R)[0].ravel()
    text = (f"K1: {rig.K0.ravel().tolist()}\nK2: {rig.K1.tolist()}\nR: {rvec.tolist()}\nT: {rig.T.tolist()}\n"
            f"image_width: {W}\nimage_height: {H}\n")
    r = read_rig(write(tmp_path, text))
    np.testing.assert_allclose(r.R, rig.R, atol=1e-12)
    assert r.size == (W, H) and np.array_equal(r.D1, np.zeros(4))


def test_size_check_names_the_field(tmp_path):
    r = read_rig(write(tmp_path, kalibr_yaml(make_rig()), "camchain.yaml"))
    r.check_size(W, H, "left.png")
    with pytest.raises(RigError, match=r"camchain.yaml: cam0.resolution: image size 320x240 does not match "
                                        r"left.png \(640x480\)"):
        r.check_size(640, 480, "left.png")


def _without(d: dict, key: str) -> dict:
    return {k: v for k, v in d.items() if k != key}


def _with(d: dict, **changes) -> dict:
    return {**d, **changes}


OPENCV_BAD = [
    (lambda f: _without(f, "K1"), r"missing field K1 \(one of K1, M1, cameraMatrix1"),
    (lambda f: _without(f, "T"), r"missing field T"),
    (lambda f: _with(f, K1=np.eye(3)[:2]), r": K1: expected 3x3 numbers, got shape \[2, 3\]"),
    (lambda f: _with(f, T=np.array([[0.1], [0.0]])), r": T: expected 3 numbers"),
    (lambda f: _with(f, D1=np.zeros((1, 6))), r": D1: the pinhole model takes 4, 5, 8, 12, 14 coefficients, got 6"),
    (lambda f: _with(f, K1=np.where(np.eye(3) > 0, np.nan, 0)), r": K1: values must be finite"),
    (lambda f: _with(f, T=np.array([[np.inf], [0], [0]])), r": T: values must be finite"),
    (lambda f: _with(f, D2=np.array([[0.1, np.nan, 0, 0, 0]])), r": D2: coefficients must be finite"),
    (lambda f: _with(f, T=np.zeros((3, 1))), r": T: zero baseline"),
    (lambda f: _with(f, R=2 * np.eye(3)), r": R: not a rotation matrix"),
    (lambda f: _with(f, R=np.diag([1.0, 1.0, -1.0])), r": R: not a rotation matrix"),
    (lambda f: _with(f, K2=np.diag([-300.0, 300.0, 1.0])), r": K2: focal lengths must be positive"),
    (lambda f: _with(f, K1=np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 2]])), r": K1: a camera matrix is"),
    (lambda f: _with(f, distortion_model="omni"), r": distortion_model: unknown distortion model 'omni'"),
    (lambda f: _with(f, distortion_model="fisheye"), r": D1: the fisheye model takes 4 coefficients, got 5"),
    (lambda f: _with(f, T=np.array([[0.0], [-0.1], [0.0]])), r": T: the second camera sits at .* not beside it"),
    (lambda f: _with(f, T=np.array([[0.1], [0.0], [0.0]])), r": T: the second camera sits 0.0996 m to the LEFT"),
    (lambda f: _with(f, imageSize=(320, 240, 3)), r": imageSize: expected 2 numbers"),
    (lambda f: _with(f, imageSize=(0, 240)), r": imageSize: image size must be two positive integers"),
    (lambda f: _with(f, M1=np.eye(3)), r": M1: K1 given twice \(also as K1"),
    (lambda f: _with(_without(f, "imageSize"), image_width=320), r"image width and height must be given together"),
    (lambda f: _with(f, K1="three hundred"), r": K1: expected numbers, got 'three hundred'"),
]


@pytest.mark.parametrize("change,message", OPENCV_BAD)
def test_bad_opencv_files_name_file_and_field(tmp_path, change, message):
    p = write(tmp_path, storage(change(opencv_fields())))
    with pytest.raises(RigError, match=message) as e:
        read_rig(p)
    assert str(e.value).startswith(str(p)) and "\n" not in str(e.value), str(e.value)


def _cam(f: dict, cam: str, **changes) -> dict:
    out = {k: dict(v) for k, v in f.items()}
    out[cam].update(changes)
    for k, v in changes.items():
        if v is None:
            del out[cam][k]
    return out


T_SHIFT = [[1.0, 0, 0, -0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
KALIBR_BAD = [
    (lambda f: {"cam0": f["cam0"]}, r": missing field cam1 \(a Kalibr camchain has cam0 and cam1\)"),
    (lambda f: _cam(f, "cam0", intrinsics=None), r": cam0.intrinsics: missing field"),
    (lambda f: _cam(f, "cam0", intrinsics=[250.0, 250.0, 160.0]), r": cam0.intrinsics: expected 4 numbers"),
    (lambda f: _cam(f, "cam1", intrinsics=[250.0, float("nan"), 160.0, 120.0]),
     r": cam1.intrinsics: values must be finite"),
    (lambda f: _cam(f, "cam0", distortion_model="fov"), r": cam0.distortion_model: unknown distortion model 'fov'"),
    (lambda f: _cam(f, "cam1", camera_model="omni"), r": cam1.camera_model: only pinhole cameras are supported"),
    (lambda f: _cam(f, "cam1", T_cn_cnm1=None), r": cam1.T_cn_cnm1: missing field"),
    (lambda f: _cam(f, "cam1", T_cn_cnm1=T_SHIFT[:3]), r": cam1.T_cn_cnm1: expected 4x4 numbers, got shape \[3, 4\]"),
    (lambda f: _cam(f, "cam1", T_cn_cnm1=T_SHIFT[:3] + [[0, 0, 1, 1]]), r": cam1.T_cn_cnm1: the last row"),
    (lambda f: _cam(f, "cam1", T_cn_cnm1=np.eye(4).tolist()), r": cam1.T_cn_cnm1: zero baseline"),
    (lambda f: _cam(f, "cam1", resolution=[640, 480]), r": cam1.resolution: both cameras need one image size"),
    (lambda f: _cam(f, "cam0", resolution=[0, 240]), r": cam0.resolution: image size must be two positive"),
    (lambda f: _cam(f, "cam0", distortion_coeffs=[0.1, "x", 0, 0]), r": cam0.distortion_coeffs: expected"),
    (lambda f: _cam(f, "cam0", distortion_coeffs=[0.1, 0.2, 0.0]), r": cam0.distortion_coeffs: the pinhole model"),
    (lambda f: _cam(f, "cam0", distortion_coeffs=None), r": cam0.distortion_coeffs: missing field"),
    (lambda f: _cam(f, "cam1", distortion_model="equidistant"), r": cam1.distortion_model: both cameras need one "
                                                                 r"lens model, got 'radtan' and 'equidistant'"),
]


@pytest.mark.parametrize("change,message", KALIBR_BAD)
def test_bad_kalibr_files_name_file_and_field(tmp_path, change, message):
    p = write(tmp_path, yaml.safe_dump(change(kalibr_fields())), "camchain.yaml")
    with pytest.raises(RigError, match=message) as e:
        read_rig(p)
    assert str(e.value).startswith(str(p)) and "\n" not in str(e.value), str(e.value)


def test_kalibr_none_distortion_is_pinhole(tmp_path):
    f = kalibr_fields()
    for cam in ("cam0", "cam1"):
        f[cam]["distortion_model"] = "none"
        del f[cam]["distortion_coeffs"]
    r = read_rig(write(tmp_path, yaml.safe_dump(f), "camchain.yaml"))
    assert r.model == PINHOLE and not r.D1.any() and not r.D2.any()


@pytest.mark.parametrize("text,message", [
    ("cam0: [1, 2\n  x: {\n", r"not a readable YAML file"),
    ("hello world\n", r"not an OpenCV FileStorage YAML/XML file \(.*Only collections"),
    ("", r"not an OpenCV FileStorage YAML/XML file"),
    ("K1: [1, 2\n", r"not an OpenCV FileStorage YAML/XML file \(.*Missing , between the elements"),
    (b"cam0:\n  x: \xff\xfe\n", r"not a readable YAML file"),
])
def test_unreadable_files(tmp_path, text, message):
    p = write(tmp_path, text)
    with pytest.raises(RigError, match=message) as e:
        read_rig(p)
    assert str(e.value).startswith(str(p)) and "\n" not in str(e.value), str(e.value)


def test_file_count_missing_file_units_and_duplicates_across_files(tmp_path):
    with pytest.raises(RigError, match=r"nope.yml: calibration file not found"):
        read_rig(tmp_path / "nope.yml")
    a = write(tmp_path, storage(opencv_fields()), "a.yml")
    with pytest.raises(RigError, match=r"--rig: give one calibration file or two"):
        read_rig([a, a, a])
    with pytest.raises(RigError, match=r"--rig-units: expected one of cm, m, mm, got 'km'"):
        read_rig(a, units="km")
    b = write(tmp_path, storage({"T": np.array([[-0.1], [0], [0]])}), "b.yml")
    with pytest.raises(RigError, match=r"b.yml: T: T given twice \(also as T in .*a.yml\)"):
        read_rig([a, b])
    k = write(tmp_path, kalibr_yaml(make_rig()), "camchain.yaml")
    with pytest.raises(RigError, match=r"camchain.yaml: a Kalibr camchain is one file"):
        read_rig([k, a])
