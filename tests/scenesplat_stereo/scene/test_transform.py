"""A scene under p -> k R p + t (scenesplat_stereo.scene.transform), in float64 numpy: the SH band matrices
(orthogonal, composing like rotations), colours seen along turned directions against a float64 evaluation of the
basis, means, orientations and sizes against matrices written here."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from scenesplat_stereo.scene.gaussians import GaussianScene
from scenesplat_stereo.scene.harmonics import sh_basis
from scenesplat_stereo.scene.transform import (
    quaternion_left_matrix,
    rotation_to_quaternion,
    sh_rotation,
    transform_scene,
)


def random_rotation(rng, angle=None) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return cv2.Rodrigues(axis * (rng.uniform(0, np.pi) if angle is None else angle))[0]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] of wxyz quaternions [N, 4] (any norm), the textbook formula."""
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def random_scene(n: int, degree: int, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    sh = rng.normal(size=(n, (degree + 1) ** 2, 3)) * 0.4
    return GaussianScene(rng.normal(size=(n, 3)).astype(np.float32), (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                         rng.uniform(0.01, 0.1, (n, 3)).astype(np.float32), rng.uniform(0.1, 0.9, n).astype(np.float32),
                         sh.astype(np.float32), degree)


def colour(degree: int, sh: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Float64 colour before the clamp: sum_k sh[n, k] Y_k(d_n) + 0.5."""
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.einsum("nk,nkc->nc", sh_basis(degree, d), sh.astype(np.float64)) + 0.5


def test_band_matrices_are_orthogonal_and_compose():
    rng = np.random.default_rng(1)
    A, B = random_rotation(rng), random_rotation(rng)
    for degree in (1, 2, 3):
        MA, MB = sh_rotation(A, degree), sh_rotation(B, degree)
        np.testing.assert_allclose(MA @ MA.T, np.eye((degree + 1) ** 2), atol=1e-12)
        np.testing.assert_allclose(sh_rotation(A @ B, degree), MA @ MB, atol=1e-12)   # turn by B, then by A
    np.testing.assert_allclose(sh_rotation(np.eye(3), 3), np.eye(16), atol=1e-13)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_colour_along_a_turned_direction_is_the_original_colour(degree):
    """c_new(d) = c_old(R^T d), scaling and moving the scene aside (float32 storage: 1e-5)."""
    rng = np.random.default_rng(degree)
    scene = random_scene(60, degree, seed=degree)
    R = random_rotation(rng)
    out = transform_scene(scene, R, 0.37, (1.0, -2.0, 0.5))
    d = rng.normal(size=(60, 3))
    np.testing.assert_allclose(colour(degree, out.sh, d), colour(degree, scene.sh, d @ R), atol=1e-5)
    assert np.array_equal(out.sh[:, 0], scene.sh[:, 0])        # the DC term does not turn


def test_means_orientations_and_sizes_follow_the_similarity():
    rng = np.random.default_rng(2)
    scene = random_scene(40, 2, seed=3)
    for angle in (None, np.pi, 1e-9):                           # a generic rotation, a half turn, almost nothing
        R, k, t = random_rotation(rng, angle), 0.05, np.array([2.0, 3.0, 0.7])
        q = rotation_to_quaternion(R)
        np.testing.assert_allclose(quat_to_matrix(q[None])[0], R, atol=1e-14)
        out = transform_scene(scene, R, k, t)
        np.testing.assert_allclose(out.means, k * scene.means.astype(np.float64) @ R.T + t, atol=1e-6)
        np.testing.assert_allclose(quat_to_matrix(out.quats.astype(np.float64)),
                                   R @ quat_to_matrix(scene.quats.astype(np.float64)), atol=1e-6)
        np.testing.assert_allclose(np.log(out.scales), np.log(scene.scales) + math.log(k), atol=1e-6)
        assert np.array_equal(out.opacities, scene.opacities)


def test_the_left_product_matrix_is_the_hamilton_product():
    a, b = np.array([0.5, 0.5, -0.5, 0.5]), np.array([0.3, 0.1, -0.7, 0.2])
    # (w1 w2 - v1.v2, w1 v2 + w2 v1 + v1 x v2)
    want = np.concatenate([[a[0] * b[0] - a[1:] @ b[1:]], a[0] * b[1:] + b[0] * a[1:] + np.cross(a[1:], b[1:])])
    np.testing.assert_allclose(quaternion_left_matrix(a) @ b, want, atol=1e-15)


def test_bad_transforms_are_refused():
    scene = random_scene(3, 1)
    with pytest.raises(ValueError, match="R must be a 3x3 rotation matrix"):
        transform_scene(scene, np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="scale must be a finite number > 0"):
        transform_scene(scene, np.eye(3), 0.0)
    with pytest.raises(ValueError, match="offset must be 3 finite numbers"):
        transform_scene(scene, np.eye(3), 1.0, (0.0, np.nan, 0.0))
