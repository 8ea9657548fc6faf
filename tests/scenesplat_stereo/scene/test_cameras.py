"""Camera conventions (SPEC sections 1 and 4), checked against hand-written references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scenesplat_stereo.scene.cameras import (OPENGL_TO_OPENCV, fibonacci_directions, intrinsics_matrix, look_at,
                                             opengl_to_opencv, orbit_poses, orthonormalize, rigid_error,
                                             scale_intrinsics, stereo_rig, translation, viewmats_from_c2w)


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = q, rng.normal(size=3) * 3
    return pose


def _project(c2w: np.ndarray, K: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Pixel coordinates of a world point: independent of viewmats_from_c2w (uses np.linalg.inv)."""
    p = np.linalg.inv(c2w) @ np.append(point, 1.0)
    uvw = K @ p[:3]
    return uvw[:2] / uvw[2]


def test_opengl_to_opencv_known_pose():
    # An OpenGL camera at the origin with identity rotation looks down world -z, y up.
    gl = np.eye(4)
    cv = opengl_to_opencv(gl)
    np.testing.assert_array_equal(cv[:3, :3], np.diag([1.0, -1.0, -1.0]))
    ahead = np.array([0.0, 0.0, -2.0, 1.0])  # in front of the OpenGL camera
    above = np.array([0.0, 1.0, -2.0, 1.0])  # above the optical axis
    view = viewmats_from_c2w(cv)
    assert (view @ ahead)[2] == pytest.approx(2.0)  # OpenCV: in front means +z
    assert (view @ above)[1] < 0  # OpenCV: up in the image means -y
    np.testing.assert_array_equal(OPENGL_TO_OPENCV, np.diag([1.0, -1.0, -1.0, 1.0]))


def test_opengl_to_opencv_keeps_centre_and_is_involution():
    rng = np.random.default_rng(0)
    poses = np.stack([_random_pose(rng) for _ in range(5)])
    cv = opengl_to_opencv(poses)
    np.testing.assert_allclose(cv[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_allclose(opengl_to_opencv(cv), poses)
    np.testing.assert_allclose(cv[:, :3, 2], -poses[:, :3, 2])  # forward flips
    with pytest.raises(ValueError, match="4, 4"):
        opengl_to_opencv(np.eye(3))


def test_viewmats_inverse_of_c2w():
    rng = np.random.default_rng(1)
    poses = np.stack([_random_pose(rng) for _ in range(6)]).reshape(2, 3, 4, 4)
    view = viewmats_from_c2w(poses)
    np.testing.assert_allclose(view @ poses, np.broadcast_to(np.eye(4), poses.shape), atol=1e-12)


def test_look_at_axes():
    eye, target = np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 8.0])
    c2w = look_at(eye, target)  # default up (0, -1, 0): a y-down world
    np.testing.assert_allclose(c2w[:3, :3], np.eye(3), atol=1e-12)  # looking along +z with y down
    np.testing.assert_allclose(c2w[:3, 3], eye)
    # z-up world: camera at the origin looking along +y; image "up" must be world +z.
    c2w = look_at(np.zeros(3), np.array([0.0, 5.0, 0.0]), up=(0.0, 0.0, 1.0))
    np.testing.assert_allclose(c2w[:3, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 0], [1, 0, 0], atol=1e-12)
    K = intrinsics_matrix(100, 100, 50, 40)
    np.testing.assert_allclose(_project(c2w, K, np.array([0.0, 5.0, 0.0])), [50, 40], atol=1e-9)
    assert _project(c2w, K, np.array([0.0, 5.0, 1.0]))[1] < 40  # above -> smaller v
    assert rigid_error(c2w) < 1e-12


@pytest.mark.parametrize("target,up", [((0, 0, 0), (0, -1, 0)), ((0, 3, 0), (0, -1, 0))])
def test_look_at_degenerate(target, up):
    with pytest.raises(ValueError):
        look_at(np.zeros(3), np.array(target, dtype=float), up)


def test_intrinsics_scaling_pixel_centres():
    K = intrinsics_matrix(500.0, 480.0, 320.0, 240.0)
    K2 = scale_intrinsics(K, (640, 480), (320, 120))
    np.testing.assert_allclose(K2, [[250, 0, 160], [0, 120, 60], [0, 0, 1]])
    # Pixel centre (u + 0.5, v + 0.5) of a pixel at full size lies at the same ray as the continuous
    # position scaled by (W2/W, H2/H): (1, 1) px covers [0,1)^2 -> its centre 0.5 maps to 0.25 / 0.125.
    ray = np.linalg.inv(K) @ np.array([0.5, 0.5, 1.0])
    np.testing.assert_allclose(np.linalg.inv(K2) @ np.array([0.25, 0.125, 1.0]), ray)
    # The image centre stays the centre; a batch scales alike; round trip is exact.
    np.testing.assert_allclose(scale_intrinsics(intrinsics_matrix(10, 10, 32, 12), (64, 24), (96, 40))[:2, 2],
                               [48, 20])
    batch = np.stack([K, K])
    np.testing.assert_allclose(scale_intrinsics(batch, (640, 480), (320, 120)), np.stack([K2, K2]))
    np.testing.assert_allclose(scale_intrinsics(K2, (320, 120), (640, 480)), K)
    with pytest.raises(ValueError, match="positive"):
        scale_intrinsics(K, (640, 480), (0, 10))


def test_fibonacci_directions_match_spec():
    u = fibonacci_directions(10)
    assert u.shape == (10, 3)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for j in range(10):  # the SPEC formula, written out per element
        y = 1.0 - 2.0 * (j + 0.5) / 10
        r = math.sqrt(1.0 - y * y)
        np.testing.assert_allclose(u[j], [r * math.cos(j * golden), y, r * math.sin(j * golden)], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(u[:, 1], [0.9, 0.7, 0.5, 0.3, 0.1, -0.1, -0.3, -0.5, -0.7, -0.9], atol=1e-15)
    np.testing.assert_allclose(u[0], [math.sqrt(0.19), 0.9, 0.0], atol=1e-15)  # phi_0 = 0
    assert len({tuple(np.round(v, 9)) for v in u}) == 10
    assert fibonacci_directions(1).tolist() == [[1.0, 0.0, 0.0]]
    with pytest.raises(ValueError):
        fibonacci_directions(0)


def test_stereo_rig_formula():
    rng = np.random.default_rng(2)
    left = _random_pose(rng)
    u = fibonacci_directions(10)
    right, targets = stereo_rig(left, 0.1, 0.3, u)
    R, t = left[:3, :3], left[:3, 3]
    np.testing.assert_allclose(right[:3, :3], R)
    np.testing.assert_allclose(right[:3, 3], t + 0.1 * R[:, 0])  # along the camera's x axis
    assert targets.shape == (10, 4, 4)
    for j in range(10):
        T = np.eye(4)
        T[:3, 3] = 0.3 * u[j]
        np.testing.assert_allclose(targets[j], left @ T)
        np.testing.assert_allclose(targets[j][:3, :3], R)
        assert np.linalg.norm(targets[j][:3, 3] - t) == pytest.approx(0.3)
    # In the left camera's frame the right camera is at (B, 0, 0) and target j at rho u_j.
    view = viewmats_from_c2w(left)
    np.testing.assert_allclose((view @ right)[:3, 3], [0.1, 0, 0], atol=1e-12)
    np.testing.assert_allclose((view @ targets)[:, :3, 3], 0.3 * u, atol=1e-12)
    # A rectified pair: a world point projects to the same row in both images, disparity f B / z.
    K = intrinsics_matrix(200, 200, 32, 24)
    point = left @ np.array([0.2, -0.1, 2.0, 1.0])
    pl, pr = _project(left, K, point[:3]), _project(right, K, point[:3])
    assert pl[1] == pytest.approx(pr[1])
    assert pl[0] - pr[0] == pytest.approx(200 * 0.1 / 2.0)


def test_stereo_rig_batched_and_zero():
    rng = np.random.default_rng(3)
    lefts = np.stack([_random_pose(rng) for _ in range(4)])
    u = fibonacci_directions(10)[:3]
    right, targets = stereo_rig(lefts, 0.05, 0.1, u)
    assert right.shape == (4, 4, 4) and targets.shape == (4, 3, 4, 4)
    for i in range(4):
        r1, t1 = stereo_rig(lefts[i], 0.05, 0.1, u)
        np.testing.assert_allclose(right[i], r1)
        np.testing.assert_allclose(targets[i], t1)
    r0, t0 = stereo_rig(lefts[0], 0.0, 0.0, u)
    np.testing.assert_allclose(r0, lefts[0])
    np.testing.assert_allclose(t0, np.broadcast_to(lefts[0], (3, 4, 4)))


def test_orbit_poses_look_at_centre():
    center = np.array([0.3, -1.1, 0.2])
    poses = orbit_poses(center, 6.0, 8, elevation_deg=20.0, up=(0.0, -1.0, 0.0))
    assert poses.shape == (8, 4, 4)
    assert rigid_error(poses).max() < 1e-12
    K = intrinsics_matrix(100, 100, 50, 40)
    for c2w in poses:
        assert np.linalg.norm(c2w[:3, 3] - center) == pytest.approx(6.0)
        np.testing.assert_allclose(_project(c2w, K, center), [50, 40], atol=1e-9)
        # 20 degrees "above" (towards up = -y) the centre's plane
        assert -(c2w[1, 3] - center[1]) == pytest.approx(6.0 * math.sin(math.radians(20)))
    azimuths = np.arctan2(poses[:, 2, 3] - center[2], poses[:, 0, 3] - center[0])
    steps = np.diff(np.unwrap(azimuths))
    np.testing.assert_allclose(np.abs(steps), 2 * math.pi / 8, atol=1e-9)
    with pytest.raises(ValueError):
        orbit_poses(center, 0.0, 8)
    with pytest.raises(ValueError):
        orbit_poses(center, 1.0, 8, elevation_deg=90.0)


def test_rigid_error_and_orthonormalize():
    rng = np.random.default_rng(4)
    pose = _random_pose(rng)
    assert rigid_error(pose) < 1e-12
    scaled = pose.copy()
    scaled[:3, :3] *= 1.1
    assert rigid_error(scaled) > 0.1
    mirrored = pose @ np.diag([-1.0, 1, 1, 1])
    assert rigid_error(mirrored) == np.inf
    nan = pose.copy()
    nan[0, 3] = np.nan
    assert rigid_error(nan) == np.inf
    noisy = pose + rng.normal(0, 1e-5, (4, 4)) * np.r_[np.ones(3), 0][:, None]
    clean = orthonormalize(noisy)
    assert rigid_error(clean) < 1e-12
    np.testing.assert_allclose(clean, pose, atol=1e-4)
    np.testing.assert_allclose(translation(np.array([1.0, 2.0, 3.0]))[:3, 3], [1, 2, 3])
