"""sgmodel.predict.viewers: the SuperSplat settings camera sees every scene point where the left camera does (a float64
model of the viewer's camera written here from its source: the scene turned 180 degrees about z, a look-at
camera with world +y up, fov horizontal in a landscape window), and cameras.json reads back through the
teachers' INRIA reader. (tests/scenesplat_stereo/scene/test_scene_files.py validates settings.json with the viewer's own validator.)"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from scenesplat_stereo.scene.trajectories import read_inria_cameras
from sgmodel.predict.viewers import horizontal_fov, supersplat_settings, write_viewer_files


def viewer_pixels(settings: dict, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Where the SuperSplat viewer draws file points [N,3] in a width x height window (pixel units)."""
    cam = settings["cameras"][0]["initial"]
    world = points * np.array([-1.0, -1.0, 1.0])  # the loader's setLocalEulerAngles(0, 0, 180)
    position, target = np.array(cam["position"]), np.array(cam["target"])
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = world - position
    x, y, z = rel @ right, rel @ up, rel @ forward
    t = math.tan(math.radians(cam["fov"]) / 2)
    tx, ty = (t, t * height / width) if width > height else (t * width / height, t)  # horizontalFov = w > h
    return np.stack([(x / (z * tx) + 1) / 2 * width, (1 - y / (z * ty)) / 2 * height], 1)


def camera_pixels(c2w: np.ndarray, K: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = (points - c2w[:3, 3]) @ c2w[:3, :3]  # R^T (X - C)
    return np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], 1)


def yaw(angle: float, centre) -> np.ndarray:
    c2w = np.eye(4)
    c, s = math.cos(angle), math.sin(angle)
    c2w[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    c2w[:3, 3] = centre
    return c2w


@pytest.mark.parametrize("width,height,c2w", [(320, 256, np.eye(4)), (448, 256, yaw(0.4, [0.3, -0.1, 0.2])),
                                              (200, 360, np.eye(4))])
def test_settings_camera_sees_the_scene_as_the_camera_does(width, height, c2w):
    f = 0.8 * max(width, height)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    settings = supersplat_settings(c2w, K, width, height, focus=2.5)
    rng = np.random.default_rng(0)
    pix = rng.uniform([0, 0], [width, height], (50, 2))
    depth = rng.uniform(0.5, 8.0, 50)
    rays = np.stack([(pix[:, 0] - K[0, 2]) / f, (pix[:, 1] - K[1, 2]) / f, np.ones(50)], 1) * depth[:, None]
    points = rays @ c2w[:3, :3].T + c2w[:3, 3]  # scene points seen at those pixels
    np.testing.assert_allclose(camera_pixels(c2w, K, points), pix, atol=1e-9)
    np.testing.assert_allclose(viewer_pixels(settings, points, width, height), pix, atol=1e-6)
    cam = settings["cameras"][0]["initial"]
    assert np.linalg.norm(np.array(cam["target"]) - cam["position"]) == pytest.approx(2.5)
    assert settings["version"] == 2 and settings["startMode"] == "default" and settings["animTracks"] == []


def test_horizontal_fov():
    assert horizontal_fov(np.array([[100.0, 0, 0], [0, 1, 0], [0, 0, 1]]), 200) == pytest.approx(90.0)


def test_viewer_files_read_back(tmp_path):
    K = np.array([[280.0, 0, 160], [0, 270.0, 128], [0, 0, 1]])
    c2w = yaw(-0.2, [0.1, 0.2, -0.3])
    paths = write_viewer_files(tmp_path, K, 320, 256, 1.7, c2w)
    assert [p.name for p in paths] == ["settings.json", "cameras.json"]
    frames, convention = read_inria_cameras(tmp_path / "cameras.json", None)
    (pose, K_read, size, name), = frames
    assert convention == "opencv" and size == (320, 256) and name == "left"
    np.testing.assert_allclose(pose, c2w, atol=1e-12)
    np.testing.assert_allclose(K_read, K)  # the INRIA layout has no principal point: the centre is assumed
    settings = json.loads((tmp_path / "settings.json").read_text())
    assert settings["cameras"][0]["initial"]["fov"] == pytest.approx(horizontal_fov(K, 320))
