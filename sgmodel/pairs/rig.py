"""A stereo rig as calibration tools deliver it (``--rig``): two cameras with their own intrinsics and lens
distortion, and the rotation and translation between them. ``sgmodel.pairs.rectify`` turns it into a rectified
pair.

Two file formats (detected from the content):

* **OpenCV FileStorage** (YAML or XML, as ``cv::FileStorage`` writes ``stereoCalibrate``'s results; read with
  ``cv2.FileStorage``). OpenCV's own sample (samples/cpp/stereo_calib.cpp) writes two files,
  ``intrinsics.yml`` (``M1 D1 M2 D2``) and ``extrinsics.yml`` (``R T R1 R2 P1 P2 Q``): give both
  (``--rig intrinsics.yml extrinsics.yml``) or one file holding every field. Field names (first found wins,
  a name given twice is refused):

  - first (left) camera matrix: ``K1``, ``M1``, ``cameraMatrix1``, ``camera_matrix1``; distortion:
    ``D1``, ``distCoeffs1``, ``dist1``, ``distortion_coefficients1`` (absent = no distortion);
  - second (right) camera: the same names with ``2``;
  - ``R``: 3x3 rotation, or a 3-vector (Rodrigues, radians); ``T``: 3-vector. A point p1 in the first
    camera's coordinates is ``R p1 + T`` in the second's (``stereoCalibrate``'s convention);
  - image size (optional, pixels): ``imageSize``, ``image_size``, ``size`` as (width, height), or
    ``image_width`` with ``image_height``, or ``width`` with ``height``;
  - lens model (optional): ``distortion_model`` = ``radtan`` / ``plumb_bob`` / ``rational_polynomial`` /
    ``pinhole`` (default: OpenCV's radial-tangential model, 4, 5, 8, 12 or 14 coefficients) or ``fisheye`` /
    ``equidistant`` (``cv2.fisheye``, 4 coefficients);
  - the rectification fields ``R1 R2 P1 P2 Q`` and anything else are ignored (we rectify ourselves).

* **Kalibr** ``camchain.yaml`` (read with PyYAML): ``cam0`` (left) and ``cam1`` (right), each with
  ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``, ``distortion_model: radtan`` (coefficients
  ``[k1, k2, r1, r2]`` = OpenCV's k1 k2 p1 p2), ``equidistant`` (``[k1, k2, k3, k4]``, OpenCV's fisheye
  model) or ``none``, ``distortion_coeffs`` and ``resolution: [width, height]``; ``cam1.T_cn_cnm1`` is the
  4x4 transform from cam0's to cam1's coordinates (p1 = T p0). Other camera models (omni, eucm, ds) and the
  fov distortion model are refused.

Conventions: OpenCV camera axes (x right, y down, z forward). Intrinsics as both tools write them, pixel
centres at integer coordinates (``sgmodel.pairs.rectify`` converts the rectified K to this project's +0.5 centres).
Translations in metres unless ``--rig-units mm|cm`` says otherwise (Kalibr writes metres; OpenCV writes the
unit of the calibration target's square size). Every problem raises ``RigError`` (a ``CalibError``) naming
the file and the field.
"""

from __future__ import annotations

import argparse
import math
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from scenesplat_stereo.scene.cameras import intrinsics_matrix
from sgmodel.pairs.calib import CalibError

#: Metres per unit of ``--rig-units``.
UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
#: Lens models: OpenCV's radial-tangential ("pinhole", cv2.*) and equidistant fisheye (cv2.fisheye.*).
PINHOLE, FISHEYE = "pinhole", "fisheye"
_DISTORTION_LENGTHS = {PINHOLE: (0, 4, 5, 8, 12, 14), FISHEYE: (0, 4)}
_OPENCV_MODELS = {"radtan": PINHOLE, "plumb_bob": PINHOLE, "rational_polynomial": PINHOLE, "pinhole": PINHOLE,
                  "fisheye": FISHEYE, "equidistant": FISHEYE}
_KALIBR_MODELS = {"radtan": PINHOLE, "equidistant": FISHEYE, "equi": FISHEYE, "none": PINHOLE}
_OPENCV_NAMES = {
    "K1": ("K1", "M1", "cameraMatrix1", "camera_matrix1"),
    "D1": ("D1", "distCoeffs1", "dist1", "distortion_coefficients1"),
    "K2": ("K2", "M2", "cameraMatrix2", "camera_matrix2"),
    "D2": ("D2", "distCoeffs2", "dist2", "distortion_coefficients2"),
    "R": ("R",), "T": ("T",),
    "size": ("imageSize", "image_size", "size"),
    "width": ("image_width", "width"), "height": ("image_height", "height"),
    "model": ("distortion_model",),
}
#: A rotation read from a text file may be off SO(3) by rounding: up to this (max |R^T R - I|) it is
#: projected onto SO(3); beyond it the file is refused.
ROTATION_TOLERANCE = 1e-3


class RigError(CalibError):
    """Bad stereo-rig calibration; the message names the file (or flag) and the field."""


@dataclass(frozen=True)
class StereoRig:
    """Two calibrated cameras (float64). K1, K2 [3,3] pixels (integer pixel centres); D1, D2 distortion
    coefficients of ``model`` (``PINHOLE``: OpenCV k1 k2 p1 p2 [k3 ...]; ``FISHEYE``: k1..k4); R [3,3] and
    T [3] (metres) with p_right = R p_left + T; size (width, height) of the images it was calibrated at, or
    None when the file does not say (size_field: where it says); source names the file(s)."""

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    model: str = PINHOLE
    size: tuple[int, int] | None = None
    source: str = ""
    size_field: str = ""

    @property
    def baseline(self) -> float:
        """Distance between the two camera centres, metres."""
        return float(np.linalg.norm(self.T))

    def check_size(self, width: int, height: int, image: str) -> None:
        """RigError when the rig states a size other than the image's (width x height pixels)."""
        if self.size is not None and tuple(self.size) != (width, height):
            raise RigError(f"{self.size_field}: image size {self.size[0]}x{self.size[1]} does not match {image} "
                           f"({width}x{height}); the calibration holds for images of its own size only")


def add_arguments(parser: argparse.ArgumentParser, required: bool = False) -> None:
    """``--rig FILE [FILE]`` and ``--rig-units``, shared by ``sgmodel predict`` and ``sgmodel rectify``."""
    parser.add_argument("--rig", nargs="+", metavar="FILE", required=required,
                        help="raw stereo calibration: OpenCV FileStorage YAML/XML from stereoCalibrate (one file, or "
                             "intrinsics.yml extrinsics.yml) or a Kalibr camchain.yaml; the pair is rectified for you "
                             "and predict's scene.ply comes back in the raw left camera's frame (docs/calibration.md)")
    parser.add_argument("--rig-units", choices=sorted(UNITS), default="m",
                        help="unit of the rig's translation T (default m; OpenCV's is that of the target's squares)")


def read_rig(paths: str | Path | list, units: str = "m") -> StereoRig:
    """Read a stereo rig from one file (OpenCV FileStorage or Kalibr camchain) or two OpenCV files (the
    intrinsics and the extrinsics of OpenCV's stereo_calib sample); T is scaled from ``units`` to metres."""
    paths = [Path(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths)]
    if not 1 <= len(paths) <= 2:
        raise RigError(f"--rig: give one calibration file or two (intrinsics, extrinsics), got {len(paths)}")
    if units not in UNITS:
        raise RigError(f"--rig-units: expected one of {', '.join(sorted(UNITS))}, got {units!r}")
    texts = []
    for p in paths:
        try:
            texts.append(p.read_bytes())
        except FileNotFoundError:
            raise RigError(f"{p}: calibration file not found") from None
        except OSError as e:
            raise RigError(f"{p}: cannot read the calibration file: {e.strerror or e}") from None
    ros = [p for p, t in zip(paths, texts) if re.search(rb"^camera_matrix\s*:", t, re.M)
           and re.search(rb"^projection_matrix\s*:", t, re.M)]
    if ros:
        what = "are ROS camera_info files" if len(ros) > 1 else "is a ROS camera_info file"
        raise RigError(f"{' and '.join(map(str, ros))} {what} (one camera each, from camera_calibration): they hold "
                       f"no stereo extrinsics (R and T between the two cameras); give the stereo calibration "
                       f"(OpenCV stereoCalibrate's R and T, or Kalibr's camchain.yaml), or, for images already "
                       f"rectified with them, --calib/--intrinsics with the baseline -Tx/fx of the right "
                       f"projection_matrix")
    kalibr = [bool(re.search(rb"^cam0\s*:", t, re.M)) for t in texts]
    if any(kalibr):
        if len(paths) != 1:
            raise RigError(f"{paths[kalibr.index(True)]}: a Kalibr camchain is one file; give it alone")
        fields, source = _read_kalibr(paths[0], texts[0]), str(paths[0])
    else:
        fields, source = _read_opencv(paths), " + ".join(map(str, paths))
    return _make_rig(fields, UNITS[units], source)


# ------------------------------------------------------------------------------------------- OpenCV
def _open_storage(path: Path) -> cv2.FileStorage:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        text = str(e.__cause__ or e)
        m = re.search(r"in function '[^']*?\(\d+\): ([^']*)'", text) or re.search(r"error: \([^)]*\) (.*)", text)
        raise RigError(f"{path}: not an OpenCV FileStorage YAML/XML file "
                       f"({m.group(1).strip() if m else text.strip().splitlines()[0]})") from None
    if not fs.isOpened():
        raise RigError(f"{path}: cannot open as an OpenCV FileStorage file")
    return fs


def _node_values(node: cv2.FileNode, where: str):
    """An OpenCV matrix (``!!opencv-matrix``), a (nested) sequence of numbers or a number -> float64 array."""
    def values(n: cv2.FileNode):
        if n.isMap():
            try:
                mat = n.mat()
            except cv2.error:
                mat = None
            if mat is None:
                raise RigError(f"{where}: expected a matrix (rows, cols, dt, data) or a list of numbers")
            return np.asarray(mat, dtype=np.float64).tolist()
        if n.isSeq():
            return [values(n.at(i)) for i in range(n.size())]
        if n.isReal() or n.isInt():
            return n.real()
        raise RigError(f"{where}: expected numbers, got {n.string()!r}")

    return _numbers(values(node), where)


def _read_opencv(paths: list[Path]) -> dict:
    """Fields K1 D1 K2 D2 R T (arrays), size, model of one or two FileStorage files, each with its place."""
    fields: dict[str, tuple[object, str]] = {}
    for path in paths:
        fs = _open_storage(path)
        try:
            keys = set(fs.root().keys())
            for field, names in _OPENCV_NAMES.items():
                for name in names:
                    if name not in keys:
                        continue
                    where = f"{path}: {name}"
                    if field in fields:
                        raise RigError(f"{where}: {field} given twice (also as {fields[field][1].split(': ')[-1]} "
                                       f"in {fields[field][1].rsplit(': ', 1)[0]})")
                    node = fs.getNode(name)
                    value = node.string() if field == "model" else _node_values(node, where)
                    fields[field] = (value, where)
        finally:
            fs.release()
    first = " + ".join(map(str, paths))
    for field in ("K1", "K2", "R", "T"):
        if field not in fields:
            names = _OPENCV_NAMES[field]
            alternatives = f" (one of {', '.join(names)})" if len(names) > 1 else ""
            raise RigError(f"{first}: missing field {field}{alternatives}")
    out = {k: fields[k] for k in ("K1", "K2", "R", "T")}
    model, where = fields.get("model", ("radtan", first))
    if model.lower() not in _OPENCV_MODELS:
        raise RigError(f"{where}: unknown distortion model {model!r} (expected one of "
                       f"{', '.join(_OPENCV_MODELS)})")
    out["model"] = (_OPENCV_MODELS[model.lower()], where)
    for d in ("D1", "D2"):
        out[d] = fields.get(d, (np.zeros(0), f"{first}: {d}"))
    if "size" in fields:
        out["size"] = fields["size"]
    elif "width" in fields or "height" in fields:
        if not ("width" in fields and "height" in fields):
            raise RigError(f"{first}: image width and height must be given together")
        out["size"] = (np.array([fields["width"][0], fields["height"][0]]).ravel(), fields["width"][1])
    return out


# ------------------------------------------------------------------------------------------- Kalibr
def _read_kalibr(path: Path, data: bytes) -> dict:
    """Fields of a Kalibr camchain.yaml (cam0 = left, cam1 = right), each with its place in the file."""
    import yaml

    try:
        doc = yaml.safe_load(data.decode("utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise RigError(f"{path}: not a readable YAML file ({' '.join(str(e).split())})") from None
    cams = []
    for name in ("cam0", "cam1"):
        cam = doc.get(name) if isinstance(doc, dict) else None
        if not isinstance(cam, dict):
            raise RigError(f"{path}: missing field {name} (a Kalibr camchain has cam0 and cam1)")
        for key in ("camera_model", "intrinsics", "distortion_model", "resolution"):
            if key not in cam:
                raise RigError(f"{path}: {name}.{key}: missing field")
        if cam["camera_model"] != "pinhole":
            raise RigError(f"{path}: {name}.camera_model: only pinhole cameras are supported, got "
                           f"{cam['camera_model']!r}")
        if str(cam["distortion_model"]).lower() not in _KALIBR_MODELS:
            raise RigError(f"{path}: {name}.distortion_model: unknown distortion model {cam['distortion_model']!r} "
                           f"(expected one of {', '.join(_KALIBR_MODELS)})")
        cams.append(cam)
    models = [_KALIBR_MODELS[str(c["distortion_model"]).lower()] for c in cams]
    if models[0] != models[1]:
        raise RigError(f"{path}: cam1.distortion_model: both cameras need one lens model, got "
                       f"{cams[0]['distortion_model']!r} and {cams[1]['distortion_model']!r}")
    out: dict[str, tuple[object, str]] = {"model": (models[0], f"{path}: cam0.distortion_model")}
    for i, (name, cam) in enumerate(zip(("cam0", "cam1"), cams), 1):
        fu, fv, pu, pv = _matrix(cam["intrinsics"], f"{path}: {name}.intrinsics", (4,))
        out[f"K{i}"] = (intrinsics_matrix(fu, fv, pu, pv), f"{path}: {name}.intrinsics")
        if str(cam["distortion_model"]).lower() == "none":
            out[f"D{i}"] = ([], f"{path}: {name}.distortion_model")
        elif "distortion_coeffs" not in cam:
            raise RigError(f"{path}: {name}.distortion_coeffs: missing field")
        else:
            out[f"D{i}"] = (cam["distortion_coeffs"], f"{path}: {name}.distortion_coeffs")
    sizes = [image_size(c["resolution"], f"{path}: {n}.resolution") for n, c in zip(("cam0", "cam1"), cams)]
    if sizes[0] != sizes[1]:
        raise RigError(f"{path}: cam1.resolution: both cameras need one image size, got {sizes[0]} and {sizes[1]}")
    out["size"] = (sizes[0], f"{path}: cam0.resolution")
    if "T_cn_cnm1" not in cams[1]:
        raise RigError(f"{path}: cam1.T_cn_cnm1: missing field (the transform from cam0 to cam1)")
    where = f"{path}: cam1.T_cn_cnm1"
    T = _matrix(cams[1]["T_cn_cnm1"], where, (4, 4))
    if tuple(T[3]) != (0.0, 0.0, 0.0, 1.0):
        raise RigError(f"{where}: the last row of a 4x4 rigid transform is [0, 0, 0, 1], got {T[3].tolist()}")
    out["R"], out["T"] = (T[:3, :3], where), (T[:3, 3], where)
    return out


# ------------------------------------------------------------------------------------------- checks
def _numbers(value, where: str) -> np.ndarray:
    """Numbers (nested lists of equal lengths) -> float64 array (RigError otherwise)."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"{where}: expected numbers in rows of equal length, got {value!r}") from None


def _matrix(value, where: str, shape: tuple[int, ...]) -> np.ndarray:
    a = _numbers(value, where)
    squeezed = a.reshape([n for n in a.shape if n != 1])
    if a.size != math.prod(shape) or (squeezed.ndim > 1 and squeezed.shape != shape):
        raise RigError(f"{where}: expected {'x'.join(map(str, shape))} numbers, got shape {list(a.shape)}")
    a = a.reshape(shape)
    if not np.isfinite(a).all():
        raise RigError(f"{where}: values must be finite, got {a.tolist()}")
    return a


def camera_matrix(value, where: str) -> np.ndarray:
    """A 3x3 camera matrix [fx s cx; 0 fy cy; 0 0 1] with positive focal lengths (RigError otherwise)."""
    K = _matrix(value, where, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RigError(f"{where}: focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if K[1, 0] != 0 or tuple(K[2]) != (0.0, 0.0, 1.0):
        raise RigError(f"{where}: a camera matrix is [fx s cx; 0 fy cy; 0 0 1], got {K.tolist()}")
    return K


def _distortion(value, where: str, model: str) -> np.ndarray:
    d = _numbers(value, where).ravel()
    if d.size not in _DISTORTION_LENGTHS[model]:
        raise RigError(f"{where}: the {model} model takes {', '.join(map(str, _DISTORTION_LENGTHS[model][1:]))} "
                       f"coefficients, got {d.size}")
    if not np.isfinite(d).all():
        raise RigError(f"{where}: coefficients must be finite, got {d.tolist()}")
    return d if d.size else np.zeros(4)


def _rotation(value, where: str) -> np.ndarray:
    a = _numbers(value, where)
    if a.size == 3:
        a = _matrix(a, where, (3,))
        return cv2.Rodrigues(a)[0]
    R = _matrix(a, where, (3, 3))
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
        raise RigError(f"{where}: not a rotation matrix (max |R^T R - I| = {err:.2g}, det = {np.linalg.det(R):.3g})")
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def image_size(value, where: str) -> tuple[int, int]:
    """(width, height) from two positive integers (RigError otherwise)."""
    s = _matrix(value, where, (2,))
    if (s < 1).any() or (s != np.round(s)).any():
        raise RigError(f"{where}: image size must be two positive integers (width, height), got {s.tolist()}")
    return int(s[0]), int(s[1])


def _make_rig(fields: dict, metres_per_unit: float, source: str) -> StereoRig:
    model = fields["model"][0]
    K1, K2 = (camera_matrix(*fields[k]) for k in ("K1", "K2"))
    D1, D2 = (_distortion(*fields[k], model) for k in ("D1", "D2"))
    R = _rotation(*fields["R"])
    T = _matrix(*fields["T"], (3,)) * metres_per_unit
    where_T = fields["T"][1]
    if np.linalg.norm(T) < 1e-9:
        raise RigError(f"{where_T}: zero baseline (the two cameras are at the same place)")
    centre = -R.T @ T                               # the right camera's centre in the left camera's frame
    if abs(centre[0]) < max(abs(centre[1]), abs(centre[2])):
        raise RigError(f"{where_T}: the second camera sits at {centre.round(4).tolist()} m from the first, not beside "
                       f"it along x: a side-by-side (horizontal) rig is needed")
    if centre[0] < 0:
        raise RigError(f"{where_T}: the second camera sits {-centre[0]:.3g} m to the LEFT of the first; cam0/K1 must "
                       f"be the left camera (swap the cameras in the calibration and --left/--right)")
    size, size_field = (image_size(*fields["size"]), fields["size"][1]) if "size" in fields else (None, "")
    return StereoRig(K1, D1, K2, D2, R, T, model, size, source, size_field)
