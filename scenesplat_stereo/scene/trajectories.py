"""Teacher trajectories read from text (SPEC section 3): nerfstudio ``transforms*.json`` and INRIA ``cameras.json``
as OpenCV c2w in world units with pixel intrinsics, and the errors every teacher file raises (``TeacherError``,
naming the file and the field). ``teachers`` finds the files; this module reads them.

``transforms*.json``: ``frames[i].transform_matrix`` c2w; ``fl_x fl_y cx cy w h`` or ``camera_angle_x`` at the
top level or per frame (cx, cy default to the image centre); OpenGL unless told ``"camera_convention":
"opencv"``. ``cameras.json`` (INRIA): ``position`` = camera centre, ``rotation`` = c2w rotation, OpenCV,
``fx fy width height``, principal point at the image centre. Frames keep the file's order.
"""

from __future__ import annotations

import json
import math
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.cameras import (intrinsics_matrix, opengl_to_opencv, orthonormalize, rigid_error,
                                             scale_intrinsics)

RIGID_TOLERANCE = 1e-3  # max |R^T R - I| accepted in a pose read from text; larger is not a rotation


class TeacherError(ValueError):
    """A malformed teacher file: ``path`` and ``field`` say where."""

    def __init__(self, path: Path, field_name: str, problem: str):
        super().__init__(f"{path.name}: {field_name}: {problem}")
        self.path = path


def read_json(path: Path) -> object:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise TeacherError(path, "file", f"unreadable JSON ({e})") from None


def finite_number(value: object, path: Path, field_name: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise TeacherError(path, field_name, f"expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise TeacherError(path, field_name, f"expected a positive number, got {value!r}")
    return float(value)


Frame = tuple[np.ndarray, np.ndarray, tuple[int, int], str]  # c2w OpenCV, K, (w, h), name


def _pose(value: object, path: Path, field_name: str) -> np.ndarray:
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TeacherError(path, field_name, "not a numeric matrix") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise TeacherError(path, field_name, f"expected a 4x4 (or 3x4) matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise TeacherError(path, field_name, "non-finite value")
    if np.linalg.det(m[:3, :3]) <= 0:
        raise TeacherError(path, field_name, "rotation has det <= 0 (a reflection or degenerate)")
    err = float(rigid_error(m))
    if err > RIGID_TOLERANCE:
        raise TeacherError(path, field_name, f"not a rigid transform (orthonormality error {err:.3g})")
    return orthonormalize(m)


def _transforms_frame(path: Path, data: dict, i: int, frame: object, conv: str) -> Frame:
    where = f"frames[{i}]"
    if not isinstance(frame, dict) or "transform_matrix" not in frame:
        raise TeacherError(path, f"{where}.transform_matrix", "missing")
    get = lambda k: frame.get(k, data.get(k))  # noqa: E731  (per-frame value, else top level)
    if get("w") is None or get("h") is None:
        raise TeacherError(path, f"{where}.w/h", "missing image size")
    w, h = (finite_number(get(k), path, f"{where}.{k}", positive=True) for k in ("w", "h"))
    if get("fl_x") is not None:
        fx = finite_number(get("fl_x"), path, f"{where}.fl_x", positive=True)
        fy = finite_number(get("fl_y") if get("fl_y") is not None else fx, path, f"{where}.fl_y", positive=True)
    elif get("camera_angle_x") is not None:
        fx = fy = 0.5 * w / math.tan(0.5 * finite_number(get("camera_angle_x"), path, f"{where}.camera_angle_x", True))
    else:
        raise TeacherError(path, f"{where}.fl_x", "missing intrinsics (fl_x or camera_angle_x)")
    cx = finite_number(get("cx"), path, f"{where}.cx") if get("cx") is not None else 0.5 * w
    cy = finite_number(get("cy"), path, f"{where}.cy") if get("cy") is not None else 0.5 * h
    pose = _pose(frame["transform_matrix"], path, f"{where}.transform_matrix")
    return (opengl_to_opencv(pose) if conv == "opengl" else pose, intrinsics_matrix(fx, fy, cx, cy),
            (round(w), round(h)), str(frame.get("file_path", f"frame_{i:06d}")))


def read_transforms(path: Path, convention: str | None) -> tuple[list[Frame], str]:
    data = read_json(path)
    if not isinstance(data, dict):
        raise TeacherError(path, "file", "expected a JSON object")
    file_conv = data.get("camera_convention")
    if file_conv not in (None, "opencv", "opengl"):
        raise TeacherError(path, "camera_convention", f"expected 'opencv' or 'opengl', got {file_conv!r}")
    if None not in (file_conv, convention) and convention != file_conv:
        raise TeacherError(path, "camera_convention", f"{file_conv!r} but scene.json says {convention!r}")
    conv = file_conv or convention or "opengl"
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise TeacherError(path, "frames", "missing or zero frames")
    return [_transforms_frame(path, data, i, f, conv) for i, f in enumerate(frames)], conv


def _inria_frame(path: Path, i: int, cam: object) -> Frame:
    where = f"[{i}]"
    if not isinstance(cam, dict):
        raise TeacherError(path, where, "expected an object")
    for key in ("position", "rotation", "fx", "fy", "width", "height"):
        if key not in cam:
            raise TeacherError(path, f"{where}.{key}", "missing")
    w, h, fx, fy = (finite_number(cam[k], path, f"{where}.{k}", positive=True) for k in ("width", "height", "fx", "fy"))
    try:
        rotation, position = np.array(cam["rotation"], dtype=float), np.array(cam["position"], dtype=float)
    except (TypeError, ValueError):
        raise TeacherError(path, f"{where}.rotation/position", "not a 3x3 matrix and a 3-vector") from None
    if rotation.shape != (3, 3):
        raise TeacherError(path, f"{where}.rotation", f"expected a 3x3 matrix, got shape {rotation.shape}")
    if position.shape != (3,):
        raise TeacherError(path, f"{where}.position", f"expected 3 numbers, got shape {position.shape}")
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    return (_pose(pose, path, f"{where}.rotation/position"), intrinsics_matrix(fx, fy, 0.5 * w, 0.5 * h),
            (round(w), round(h)), str(cam.get("img_name", f"frame_{i:06d}")))


def read_inria_cameras(path: Path, convention: str | None) -> tuple[list[Frame], str]:
    if convention == "opengl":
        raise TeacherError(path, "camera_convention", "cameras.json is OpenCV but scene.json says 'opengl'")
    data = read_json(path)
    if not isinstance(data, list) or not data:
        raise TeacherError(path, "file", "expected a non-empty list of cameras (zero frames)")
    return [_inria_frame(path, i, cam) for i, cam in enumerate(data)], "opencv"


def stack_frames(frames: list[Frame], path: Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int], list[str]]:
    """(c2w [F,4,4], Ks [F,3,3], (W, H), names) at the most common frame size; the K of frames of another
    size are rescaled to it (a counted repair, with a warning)."""
    sizes = [f[2] for f in frames]
    size = Counter(sizes).most_common(1)[0][0]
    Ks = np.stack([scale_intrinsics(f[1], f[2], size) for f in frames])
    odd = sum(s != size for s in sizes)
    if odd:
        warnings.warn(f"{path}: {odd} of {len(frames)} frames are not {size[0]}x{size[1]}; "
                      "their intrinsics were rescaled to that size", stacklevel=3)
    return np.stack([f[0] for f in frames]), Ks, size, [f[3] for f in frames]
