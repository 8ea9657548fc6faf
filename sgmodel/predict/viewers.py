"""What a viewer needs to open a predicted scene framed like the left image: the SuperSplat viewer's
``settings.json`` and the same camera in an INRIA ``cameras.json``.

Scenes are in the left camera's frame (OpenCV axes: x right, y down, z forward; metres). The SuperSplat
viewer (@playcanvas/supersplat-viewer, settings schema version 2) loads a scene rotated 180 degrees about z
(its loader calls ``setLocalEulerAngles(0, 0, 180)``), so a point (x, y, z) of the file sits at (-x, -y, z)
in the viewer's world (y up; a camera looks along its local -z), and it places its camera from
``cameras[0].initial``: ``position``, ``target`` (the orbit centre) and ``fov`` in degrees, which it
applies as the horizontal field of view in a landscape window (``camera.horizontalFov = width > height``)
and as the vertical one in a portrait window. The INRIA ``cameras.json`` (the 3DGS trainer's
``camera_to_JSON``) lists cameras with ``position`` = camera centre and ``rotation`` = the camera-to-world
rotation (OpenCV axes), ``fx``, ``fy``, ``width``, ``height``; ``scenesplat_stereo.scene.teachers`` reads it.
docs/model.md "Opening a scene in a viewer" shows both in use.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from scenesplat_stereo.common.files import atomic_write_json

#: The settings schema version written (the viewer migrates older ones, never newer).
SETTINGS_VERSION = 2
#: File (x, y, z) -> SuperSplat viewer world (-x, -y, z): the viewer's 180-degree turn about z.
VIEWER_FROM_FILE = np.diag([-1.0, -1.0, 1.0])


def horizontal_fov(K: np.ndarray, width: int) -> float:
    """2 atan(W / (2 fx)) in degrees: the horizontal field of view of a W-pixel-wide image."""
    return math.degrees(2.0 * math.atan(0.5 * width / float(K[0, 0])))


def supersplat_settings(c2w: np.ndarray, K: np.ndarray, width: int, height: int, focus: float) -> dict:
    """The viewer's settings (schema version 2) with its camera at the camera ``c2w`` [4,4] (OpenCV axes,
    in the scene's frame), looking at the point ``focus`` metres along its optical axis (the orbit centre),
    with the image's field of view: horizontal for a landscape image, vertical for a portrait one (what the
    viewer applies in a window of the same shape). Post effects off, tone mapping none, black background."""
    c2w = np.asarray(c2w, dtype=np.float64)
    centre, axis = c2w[:3, 3], c2w[:3, 2]
    fov = horizontal_fov(K, width) if width >= height else math.degrees(2.0 * math.atan(0.5 * height / K[1, 1]))
    effects = {"sharpness": {"enabled": False, "amount": 0},
               "bloom": {"enabled": False, "intensity": 0.1, "blurLevel": 2},
               "grading": {"enabled": False, "brightness": 1, "contrast": 1, "saturation": 1, "tint": [1, 1, 1]},
               "vignette": {"enabled": False, "intensity": 0.5, "inner": 0.3, "outer": 0.75, "curvature": 1},
               "fringing": {"enabled": False, "intensity": 0.5}}
    pose = {"position": (VIEWER_FROM_FILE @ centre).tolist(),
            "target": (VIEWER_FROM_FILE @ (centre + focus * axis)).tolist(), "fov": fov}
    return {"version": SETTINGS_VERSION, "tonemapping": "none", "highPrecisionRendering": False,
            "background": {"color": [0, 0, 0]}, "postEffectSettings": effects, "animTracks": [],
            "cameras": [{"initial": pose}], "annotations": [], "startMode": "default"}


def inria_cameras(c2w: np.ndarray, K: np.ndarray, width: int, height: int, name: str = "left") -> list[dict]:
    """A one-camera INRIA ``cameras.json`` list: id 0, ``img_name``, size, centre, c2w rotation, fx, fy."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return [{"id": 0, "img_name": name, "width": int(width), "height": int(height),
             "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
             "fy": float(K[1, 1]), "fx": float(K[0, 0])}]


def write_viewer_files(folder: str | Path, K: np.ndarray, width: int, height: int, focus: float,
                       c2w: np.ndarray | None = None) -> list[Path]:
    """``settings.json`` and ``cameras.json`` in ``folder`` for the camera ``c2w`` (default: the left camera,
    the identity), written atomically; their paths."""
    c2w = np.eye(4) if c2w is None else c2w
    folder = Path(folder)
    return [atomic_write_json(folder / "settings.json", supersplat_settings(c2w, K, width, height, focus)),
            atomic_write_json(folder / "cameras.json", inria_cameras(c2w, K, width, height))]
