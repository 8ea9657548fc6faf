"""The model's Gaussians in a rotated frame (sgmodel.pairs.rotate, torch tensors): SH colours against a float64
evaluation of the basis, orientations against rotation matrices, and the rasteriser's image of the rotated scene
seen by the rotated camera against the original's."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.raster.reference import quat_to_rotmat, sh_colors
from scenesplat_stereo.scene.transform import rotation_to_quaternion
from sgmodel.pairs.rotate import rotate_gaussians


def random_rotation(rng, angle=None) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return cv2.Rodrigues(axis * (rng.uniform(0, np.pi) if angle is None else angle))[0]


def random_gaussians(n: int, degree: int, seed: int = 0, dtype=torch.float64) -> dict:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(1, n, 3, generator=g, dtype=dtype) * 0.3 + torch.tensor([0, 0, 3.0], dtype=dtype)
    return dict(means=means, quats=torch.randn(1, n, 4, generator=g, dtype=dtype),
                scales=torch.rand(1, n, 3, generator=g, dtype=dtype) * 0.08 + 0.01,
                opacities=torch.rand(1, n, generator=g, dtype=dtype) * 0.8 + 0.1,
                sh=torch.randn(1, n, (degree + 1) ** 2, 3, generator=g, dtype=dtype) * 0.4)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_colour_along_a_rotated_direction_is_the_original_colour(degree):
    """c_new(d) = c_old(R^T d) for every direction d, evaluated in float64 with the rasteriser's SH basis."""
    rng = np.random.default_rng(degree)
    for _ in range(5):
        R = random_rotation(rng)
        g = random_gaussians(50, degree, seed=degree)
        g["sh"][..., 0, :] += 10.0                       # keep colours above the clamp at 0
        out = rotate_gaussians(g, R)
        d = torch.from_numpy(rng.normal(size=(50, 3)))
        new = sh_colors(degree, d, out["sh"][0])
        old = sh_colors(degree, d @ torch.from_numpy(R), g["sh"][0])   # rows (R^T d)^T
        torch.testing.assert_close(new, old, atol=1e-12, rtol=1e-12)
        assert torch.equal(out["sh"][0, :, 0], g["sh"][0, :, 0])        # the DC term does not turn


def test_means_and_orientations_turn_with_the_frame():
    rng = np.random.default_rng(2)
    for angle in (None, np.pi, 1e-9):                   # a generic rotation, a half turn, almost nothing
        R = random_rotation(rng, angle)
        q = rotation_to_quaternion(R)
        np.testing.assert_allclose(quat_to_rotmat(torch.from_numpy(q)[None])[0].numpy(), R, atol=1e-14)
        g = random_gaussians(40, 2, seed=3)
        out = rotate_gaussians(g, R)
        torch.testing.assert_close(out["means"][0], g["means"][0] @ torch.from_numpy(R).T, atol=1e-14, rtol=0)
        torch.testing.assert_close(quat_to_rotmat(out["quats"][0]), torch.from_numpy(R) @ quat_to_rotmat(g["quats"][0]),
                                   atol=1e-14, rtol=0)
        torch.testing.assert_close(out["quats"].norm(dim=-1), g["quats"].norm(dim=-1), atol=1e-14, rtol=0)
        assert out["scales"] is g["scales"] and out["opacities"] is g["opacities"]


def test_the_rasteriser_sees_the_rotated_scene_from_the_rotated_camera_as_the_original():
    """Render the scene from a camera V (world -> camera), and the rotated scene (p -> R p) from V R^T: the
    same image, up to float32 rounding."""
    R = random_rotation(np.random.default_rng(4), angle=0.6)
    g = {k: v.float() for k, v in random_gaussians(300, 2, seed=5).items()}
    out = rotate_gaussians(g, R)
    assert all(v.dtype == torch.float32 for v in out.values())
    view = torch.eye(4)
    view[:3, 3] = torch.tensor([0.1, -0.05, 0.2])
    turned = torch.eye(4, dtype=torch.float64)
    turned[:3, :3] = torch.from_numpy(R.T)
    views = [view[None], (view.double() @ turned).float()[None]]
    K = torch.tensor([[[120.0, 0, 64], [0, 120.0, 48], [0, 0, 1]]])
    images = [rasterization(s["means"][0], s["quats"][0], s["scales"][0], s["opacities"][0], s["sh"][0], v, K, 128, 96,
                            sh_degree=2)[0] for s, v in ((g, views[0]), (out, views[1]))]
    assert images[0].abs().max() > 0.3
    torch.testing.assert_close(images[1], images[0], atol=2e-5, rtol=0)


def test_bad_rotations_and_sh_sizes_are_refused():
    g = random_gaussians(3, 2)
    with pytest.raises(ValueError, match="R must be a 3x3 rotation matrix"):
        rotate_gaussians(g, np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="R must be a 3x3 rotation matrix"):
        rotate_gaussians(g, 2 * np.eye(3))
    with pytest.raises(ValueError, match=r"sh must hold \(d\+1\)\^2 coefficients"):
        rotate_gaussians({**g, "sh": torch.zeros(1, 3, 5, 3, dtype=torch.float64)}, np.eye(3))
