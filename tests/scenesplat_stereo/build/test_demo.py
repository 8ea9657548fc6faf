"""Procedural demo teachers: geometry, determinism, files that load back, and renders with texture."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenesplat_stereo.build.demo import (
    DEFAULT_NUM_GAUSSIANS,
    ROOM_SIZE,
    make_room,
    make_table,
    room_trajectory,
    write_demo_teachers,
)
from scenesplat_stereo.build.protocol import TIERS, plan_scene, tier_for_psnr
from scenesplat_stereo.scene.cameras import (
    fibonacci_directions,
    rigid_error,
    stereo_rig,
    viewmats_from_c2w,
)
from scenesplat_stereo.scene.gaussians import load_ply
from scenesplat_stereo.scene.ply import SH_C0
from scenesplat_stereo.scene.teachers import discover_teachers

SMALL = 4000  # Gaussians per room in these tests (the default is sized for the README build)


def test_default_size_in_range():
    assert 20_000 <= DEFAULT_NUM_GAUSSIANS <= 60_000
    assert ROOM_SIZE == (4.0, 5.0, 2.6)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_make_room_valid_and_deterministic(degree):
    room = make_room(7, sh_degree=degree, num_gaussians=SMALL)
    again = make_room(7, sh_degree=degree, num_gaussians=SMALL)
    assert len(room) == SMALL and room.sh_degree == degree and room.sh.shape == (SMALL, (degree + 1) ** 2, 3)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(room, name), getattr(again, name))
    eps = 1e-6
    assert (room.means >= -eps).all() and (room.means <= np.array(ROOM_SIZE) + eps).all()
    np.testing.assert_allclose(np.linalg.norm(room.quats, axis=1), 1.0, atol=1e-6)
    assert (room.scales > 0).all() and room.scales.max() < 0.3  # ~0.6 x the 0.17 m spacing of 4000
    assert (room.opacities > 0.9).all() and (room.opacities <= 1).all()
    rgb = room.sh[:, 0] * SH_C0 + 0.5
    assert (rgb >= 0).all() and (rgb <= 1).all() and rgb.std(axis=0).min() > 0.05  # coloured, not flat
    other = make_room(8, sh_degree=degree, num_gaussians=SMALL)
    assert not np.array_equal(room.means, other.means)


def test_sh_bands_tint_and_share_geometry():
    flat, tinted = make_room(3, 0, SMALL), make_room(3, 3, SMALL)
    np.testing.assert_array_equal(flat.means, tinted.means)  # geometry and DC do not depend on the degree
    np.testing.assert_array_equal(flat.sh[:, 0], tinted.sh[:, 0])
    for band in (1, 2, 3):
        coeffs = tinted.sh[:, band * band:(band + 1) ** 2]
        assert 0.005 < np.abs(coeffs).mean() < 0.2, band  # small, non-zero view dependence


def test_room_structure():
    room = make_room(11, num_gaussians=DEFAULT_NUM_GAUSSIANS)
    w, d, h = ROOM_SIZE
    m = room.means
    on_shell = (np.isclose(m[:, 0], 0) | np.isclose(m[:, 0], w) | np.isclose(m[:, 1], 0) | np.isclose(m[:, 1], d)
                | np.isclose(m[:, 2], 0) | np.isclose(m[:, 2], h))
    assert 0.55 < on_shell.mean() < 0.8  # walls, floor, ceiling
    inside = m[~on_shell]
    assert (inside[:, 2] > 0.4).mean() > 0.3  # furniture rises above the floor
    # Thin structures: Gaussians at most 2 cm wide away from the walls, stacked into vertical rods; one
    # (the lamp pole) spans 0.1 m .. 1.4 m.
    thin = (room.scales[:, :2].max(axis=1) <= 0.02) & ~on_shell
    xy = np.round(m[thin, :2], 3)
    rods = {tuple(p) for p in xy}
    assert len(rods) >= 5  # four table legs and a pole
    spans = [np.ptp(m[thin][(xy == p).all(1), 2]) for p in rods]
    assert max(spans) > 1.3 and sorted(spans)[-5] > 0.6


@pytest.mark.parametrize("seed", [0, 1, 2, 5])
def test_trajectory_smooth_and_clear_of_geometry(seed):
    c2w = room_trajectory(24, seed=seed)
    assert c2w.shape == (24, 4, 4) and rigid_error(c2w).max() < 1e-12
    eyes = c2w[:, :3, 3]
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1)
    assert steps.max() < 0.4
    cos = np.einsum("fi,fi->f", c2w[1:, :3, 2], c2w[:-1, :3, 2])
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 35
    # Every camera of the widest tier (B 0.10 m, rho 0.30 m) stays >= 0.3 m from every Gaussian.
    right, targets = stereo_rig(c2w, TIERS[-1].baseline, TIERS[-1].rho, fibonacci_directions(10))
    centres = np.concatenate([eyes, right[:, :3, 3], targets[:, :, :3, 3].reshape(-1, 3)])
    means = make_room(seed, num_gaussians=DEFAULT_NUM_GAUSSIANS).means.astype(np.float64)
    nearest = min(np.linalg.norm(means - c, axis=1).min() for c in centres)
    assert nearest > 0.3
    # looking outwards at the walls, never straight up or down
    assert np.abs(c2w[:, 2, 2]).max() < 0.5


def test_write_demo_teachers_roundtrip(tmp_path):
    out = tmp_path / "demo"
    folders = write_demo_teachers(out, n_scenes=4, seed=3, num_gaussians=SMALL, n_frames=6, width=64,
                                  height=48, progress=False)
    assert [f.name for f in folders] == [f"demo_room_{i:02d}" for i in range(4)]
    assert sorted(p.name for p in out.iterdir()) == [f.name for f in folders]  # no temporary folders left
    found = discover_teachers(out)
    assert not found.rejected and len(found.teachers) == 4
    ts = found.teachers
    assert [t.sh_degree for t in ts] == [0, 1, 2, 3]
    assert {TIERS.index(tier_for_psnr(t.psnr)) for t in ts} == {0, 1, 2}
    assert [t.camera_convention for t in ts] == ["opengl", "opencv", "opengl", "opencv"]
    for i, t in enumerate(ts):
        assert (t.layout, t.subset, t.width, t.height, t.num_frames) == ("plain", "demo", 64, 48, 6)
        np.testing.assert_allclose(t.c2w, room_trajectory(6, seed=3000 + i), atol=1e-12)
        np.testing.assert_allclose(t.Ks[0], [[0.5 * 64 / math.tan(math.radians(35)), 0, 32],
                                             [0, 0.5 * 64 / math.tan(math.radians(35)), 24], [0, 0, 1]])
        scene = load_ply(t.ply_path)
        ref = make_room(3000 + i, sh_degree=i, num_gaussians=SMALL)
        np.testing.assert_array_equal(scene.means, ref.means)
        np.testing.assert_allclose(scene.scales, ref.scales, rtol=1e-6)
        np.testing.assert_allclose(scene.sh, ref.sh)
    # Deterministic bytes; rewriting replaces the old folders.
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    write_demo_teachers(out, n_scenes=4, seed=3, num_gaussians=SMALL, n_frames=6, width=64, height=48,
                        progress=False)
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert before == after


def test_demo_teachers_render_with_texture(tmp_path):
    from scenesplat_stereo.raster import rasterization

    write_demo_teachers(tmp_path, n_scenes=2, seed=0, num_gaussians=8000, n_frames=4, width=80, height=60,
                        progress=False)
    for t in discover_teachers(tmp_path).teachers:
        plan = plan_scene(t, "val")[1]
        c2w = np.concatenate([plan.c2w_left[None], plan.c2w_right[None], plan.c2w_targets[:1]])
        g = load_ply(t.ply_path).to_torch()
        colors, alphas, _ = rasterization(
            g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
            torch.tensor(viewmats_from_c2w(c2w), dtype=torch.float32),
            torch.tensor(np.repeat(plan.K[None], 3, 0), dtype=torch.float32), plan.width, plan.height,
            sh_degree=t.sh_degree, rasterize_mode="antialiased")
        assert colors.shape == (3, 60, 80, 3)
        assert alphas.min() > 0.5 and alphas.mean() > 0.95  # inside a closed room: everything covered
        gray = colors.clamp(0, 1).mean(-1).numpy()
        assert gray.std(axis=(1, 2)).min() > 0.03  # texture, not a flat colour
        grad = np.abs(np.diff(gray, axis=2)).mean(axis=(1, 2))
        assert grad.min() > 0.005
        assert not torch.allclose(colors[0], colors[1])  # the right view differs


def test_table_stands_on_the_floor_with_its_top_at_the_height_and_footprint_asked_for():
    table = make_table(0, (2.0, 2.5), (0.8, 0.6), 0.75, 400, sh_degree=1)
    m = table.means.astype(np.float64)
    assert len(table) == 400 and table.sh_degree == 1
    assert m[:, 2].max() == pytest.approx(0.75, abs=1e-6) and m[:, 2].min() >= 0.0
    np.testing.assert_allclose(m[:, :2].min(0), [1.6, 2.2], atol=1e-6)
    np.testing.assert_allclose(m[:, :2].max(0), [2.4, 2.8], atol=1e-6)
    with pytest.raises(ValueError, match="num_gaussians must be >= 100"):
        make_table(0, (0, 0), (1, 1), 0.7, 50)
