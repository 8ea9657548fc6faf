"""Procedural indoor teacher scenes: the bundled default teachers of ``scenesplat-stereo demo-teachers``.

A room is a 4 m x 5 m x 2.6 m box in a z-up world (metres; floor z = 0, x in [0, 4], y in [0, 5]):
walls, floor and ceiling made of many small flat Gaussians whose colours follow textures (planks or
tiles, wallpaper, posters with coloured shapes) so that renders have texture for SIFT; furniture-like
boxes (cabinet, sofa, table top); thin structures (table legs, a lamp pole). SH degree 0..3: the DC term
holds the texture, higher bands a small view-dependent tint. The trajectory is a smooth loop through the
free middle of the room, looking outwards at the walls (OpenCV c2w). Everything is deterministic for a
seed.

``write_demo_teachers`` writes plain-layout teachers (``point_cloud.ply``, ``transforms.json`` in the
nerfstudio OpenGL convention, or "opencv" for some scenes, and ``scene.json`` with PSNR, subset and
camera convention), spanning the PSNR tiers and SH degrees 0..3.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenesplat_stereo.build.protocol import TIERS
from scenesplat_stereo.common.files import atomic_write_json
from scenesplat_stereo.common.ownership import StagedFolder, check_replaceable
from scenesplat_stereo.common.text import argtype, parse_size, whole_number
from scenesplat_stereo.scene.cameras import OPENGL_TO_OPENCV, intrinsics_matrix, look_at
from scenesplat_stereo.scene.gaussians import GaussianScene, save_ply
from scenesplat_stereo.scene.ply import SH_C0

ROOM_SIZE = (4.0, 5.0, 2.6)  # metres: x width, y depth, z height
MIN_GAUSSIANS = 2000  # per room: fewer leave holes in its walls
DEFAULT_NUM_GAUSSIANS = 36_000  # per room: a 256x192 build of 4 rooms stays a few minutes on 2 CPU cores
DEMO_SUBSET = "demo"
OWNER = "scenesplat-stereo demo-teachers"  # recorded in each room's manifest: a later run may replace the room
_SURFACE_SHARE, _FURNITURE_SHARE = 0.68, 0.26  # of the Gaussians; thin structures get the rest
_THICKNESS = 0.004  # m, the thin axis of a surface Gaussian
_SH_TINT = (0.10, 0.05, 0.025)  # amplitude of the view-dependent tint per SH band 1..3

Texture = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (s, t) metres on a face -> rgb [n, 3]


# ---------------------------------------------------------------------------------------------- textures
def _waves(rng: np.random.Generator, k: int = 4, scale: float = 1.0) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Smooth noise in [-1, 1]: a sum of k random plane waves with wavelengths around ``scale`` metres."""
    freq = rng.normal(size=(k, 2)) * (2 * math.pi / scale)
    phase = rng.uniform(0, 2 * math.pi, k)
    return lambda s, t: np.sin(np.outer(s, freq[:, 0]) + np.outer(t, freq[:, 1]) + phase).mean(axis=1)


def _posters(rng: np.random.Generator, s_range: float, count: int) -> list[tuple]:
    """Poster rectangles (s0, t0, w, h, background rgb, shapes) on a wall; shapes are coloured discs and
    squares (centre s, t, radius, rgb, is_square) that give blobs and corners."""
    posters = []
    for i in range(count):
        w, h = rng.uniform(0.5, 1.0), rng.uniform(0.45, 0.8)
        s0 = (i + 0.5) * s_range / count - w / 2 + rng.uniform(-0.15, 0.15)
        t0 = rng.uniform(1.0, 1.6)
        shapes = [(s0 + rng.uniform(0.1, w - 0.1), t0 + rng.uniform(0.1, h - 0.1), rng.uniform(0.05, 0.14),
                   rng.uniform(0.0, 1.0, 3), rng.random() < 0.5) for _ in range(rng.integers(4, 8))]
        posters.append((s0, t0, w, h, rng.uniform(0.7, 1.0, 3), shapes))
    return posters


def _wall_texture(rng: np.random.Generator, s_range: float) -> Texture:
    base = rng.uniform(0.45, 0.85, 3)
    accent = np.clip(base * rng.uniform(0.6, 0.9) + rng.normal(0, 0.05, 3), 0, 1)
    period, kind, noise = rng.uniform(0.18, 0.35), rng.integers(0, 3), _waves(rng, scale=0.6)
    posters = _posters(rng, s_range, int(rng.integers(1, 4)))

    def texture(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        if kind == 0:  # vertical stripes
            mix = (np.floor(s / period) % 2)[:, None]
        elif kind == 1:  # diamond lattice
            mix = ((np.floor((s + t) / period) + np.floor((s - t) / period)) % 2)[:, None]
        else:  # plain paint with a dado rail
            mix = ((t > 0.85) & (t < 0.92)).astype(float)[:, None]
        rgb = base * (1 - mix) + accent * mix + 0.05 * noise(s, t)[:, None]
        for s0, t0, w, h, bg, shapes in posters:
            inside = (s > s0) & (s < s0 + w) & (t > t0) & (t < t0 + h)
            frame = inside & ~((s > s0 + 0.03) & (s < s0 + w - 0.03) & (t > t0 + 0.03) & (t < t0 + h - 0.03))
            rgb[inside] = bg
            for cs, ct, r, col, square in shapes:
                d = np.maximum(np.abs(s - cs), np.abs(t - ct)) if square else np.hypot(s - cs, t - ct)
                rgb[inside & (d < r)] = col
            rgb[frame] = 0.08
        return rgb

    return texture


def _floor_texture(rng: np.random.Generator) -> Texture:
    wood = rng.uniform([0.45, 0.28, 0.12], [0.7, 0.45, 0.25])
    tile_a, tile_b = rng.uniform(0.6, 0.9, 3), rng.uniform(0.1, 0.4, 3)
    planks, width, grain = rng.random() < 0.5, rng.uniform(0.15, 0.25), _waves(rng, scale=0.3)

    def texture(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        if planks:
            row = np.floor(t / width)
            offset = (row * 0.37) % 1.0 * 1.2
            plank = np.floor((s + offset) / 1.2) + 7 * row
            tone = 0.75 + 0.25 * np.sin(plank * 12.9898) ** 2
            rgb = wood * (tone + 0.08 * grain(s * 0.2, t * 3.0))[:, None]
            seam = ((t % width) < 0.012) | (((s + offset) % 1.2) < 0.012)
            rgb[seam] *= 0.35
            return rgb
        checker = ((np.floor(s / 0.3) + np.floor(t / 0.3)) % 2)[:, None]
        rgb = tile_a * checker + tile_b * (1 - checker)
        grout = ((s % 0.3) < 0.01) | ((t % 0.3) < 0.01)
        rgb[grout] = 0.55
        return rgb

    return texture


def _plain_texture(rng: np.random.Generator, colour: np.ndarray, stripe: float = 0.0) -> Texture:
    noise = _waves(rng, scale=0.4)

    def texture(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        rgb = np.broadcast_to(colour, (len(s), 3)) * (1 + 0.1 * noise(s, t))[:, None]
        if stripe:  # shelf edges / panel seams every ``stripe`` metres
            rgb = np.where(((t % stripe) < 0.025)[:, None], rgb * 0.4, rgb)
        return rgb

    return texture


# ------------------------------------------------------------------------------------------ primitives
def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions [..., 4]."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - (av * bv).sum(-1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1)


# Rotations taking the local z axis (a flat Gaussian's thin axis) to the world x, y or z axis (wxyz).
_ALIGN_Z_TO = {0: (math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0), 1: (math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0),
               2: (1.0, 0.0, 0.0, 0.0)}


def _spin(rng: np.random.Generator, axis: int, n: int) -> np.ndarray:
    """Unit quaternions [n, 4]: a random rotation about local z, then local z onto world ``axis``."""
    half = rng.uniform(0, math.pi, n)
    spin = np.stack([np.cos(half), np.zeros(n), np.zeros(n), np.sin(half)], -1)
    return _quat_mul(np.broadcast_to(np.array(_ALIGN_Z_TO[axis]), (n, 4)), spin)


class _Builder:
    """Collects Gaussians part by part; colours are rgb in [0, 1], later turned into SH."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.parts: list[tuple[np.ndarray, ...]] = []

    def plane(self, axis: int, at: float, lo: tuple[float, float], hi: tuple[float, float], count: int,
              texture: Texture, opacity: float = 0.98) -> None:
        """``count`` flat Gaussians tiling the axis-aligned rectangle {x_axis = at, lo <= (s, t) <= hi},
        (s, t) the other two world axes in increasing order, on a jittered grid."""
        if count <= 0:
            return
        rng, (ls, lt), (hs, ht) = self.rng, lo, hi
        ns = min(count, max(1, round(math.sqrt(count * (hs - ls) / (ht - lt)))))
        nt = max(1, count // ns)
        gi, gj = np.meshgrid(np.arange(ns), np.arange(nt), indexing="ij")
        u = np.concatenate([(gi.ravel() + rng.random(ns * nt)) / ns, rng.random(count - ns * nt)])
        v = np.concatenate([(gj.ravel() + rng.random(ns * nt)) / nt, rng.random(count - ns * nt)])
        s, t = ls + u * (hs - ls), lt + v * (ht - lt)
        means = np.insert(np.stack([s, t], -1), axis, at, axis=1)
        spacing = math.sqrt((hs - ls) * (ht - lt) / count)
        scales = np.column_stack([0.7 * spacing * rng.uniform(0.8, 1.25, (count, 2)), np.full(count, _THICKNESS)])
        rgb = texture(s, t) + rng.normal(0, 0.03, (count, 3))
        self.parts.append((means, _spin(rng, axis, count), scales, np.full(count, opacity), rgb))

    def box(self, lo: tuple[float, float, float], hi: tuple[float, float, float], count: int,
            texture: Texture) -> None:
        """A closed box (no bottom face) of ``count`` Gaussians shared by area."""
        lo_a, hi_a = np.array(lo), np.array(hi)
        ext = hi_a - lo_a
        faces = [(a, side) for a in range(3) for side in (0, 1) if not (a == 2 and side == 0)]
        areas = np.array([np.prod(np.delete(ext, a)) for a, _ in faces])
        for (a, side), n in zip(faces, _shares(count, areas)):
            other = [i for i in range(3) if i != a]
            self.plane(a, (hi_a if side else lo_a)[a], tuple(lo_a[other]), tuple(hi_a[other]), n, texture)

    def rod(self, base: tuple[float, float, float], height: float, radius: float, count: int,
            rgb: np.ndarray) -> None:
        """A thin vertical rod (table leg, lamp pole): Gaussians on its axis, elongated along it."""
        z = base[2] + (np.arange(count) + 0.5) / count * height
        means = np.column_stack([np.full(count, base[0]), np.full(count, base[1]), z])
        scales = np.column_stack([np.full((count, 2), radius), np.full(count, 0.7 * height / count)])
        colours = rgb + self.rng.normal(0, 0.02, (count, 3))
        self.parts.append((means, _spin(self.rng, 2, count), scales, np.full(count, 0.99), colours))


def _shares(total: int, weights: np.ndarray) -> list[int]:
    """Split ``total`` into integers proportional to ``weights`` (largest remainders), summing to it."""
    raw = total * np.asarray(weights, dtype=np.float64) / np.sum(weights)
    out = np.floor(raw).astype(int)
    out[np.argsort(-(raw - out), kind="stable")[: total - out.sum()]] += 1
    return out.tolist()


# ------------------------------------------------------------------------------------------------ room
def make_room(seed: int, sh_degree: int = 0, num_gaussians: int = DEFAULT_NUM_GAUSSIANS,
              size: tuple[float, float, float] = ROOM_SIZE) -> GaussianScene:
    """A procedural room of exactly ``num_gaussians`` Gaussians (metres, z up, floor at z = 0, x in
    [0, W], y in [0, D]): textured walls, floor and ceiling; a cabinet, a sofa, a table with four thin
    legs and a lamp with a thin pole, placed along the walls (mirrored and shifted per seed) so that
    ``room_trajectory`` stays clear of them. SH degree 0..3 (higher bands: a small view-dependent tint).
    """
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"make_room: sh_degree must be in 0..3, got {sh_degree}")
    if num_gaussians < MIN_GAUSSIANS:
        raise ValueError(f"make_room: num_gaussians must be >= {MIN_GAUSSIANS} to cover the room, got {num_gaussians}")
    rng = np.random.default_rng(seed)
    w, d, h = size
    b = _Builder(rng)
    n_surf, n_furn = int(_SURFACE_SHARE * num_gaussians), int(_FURNITURE_SHARE * num_gaussians)
    n_thin = num_gaussians - n_surf - n_furn
    # Walls, floor, ceiling (the ceiling is plain, so it gets half the density).
    surfaces = [(0, 0.0, (0, 0), (d, h)), (0, w, (0, 0), (d, h)), (1, 0.0, (0, 0), (w, h)),
                (1, d, (0, 0), (w, h)), (2, 0.0, (0, 0), (w, d)), (2, h, (0, 0), (w, d))]
    areas = [(hi[0] - lo[0]) * (hi[1] - lo[1]) * (0.5 if axis == 2 and at > 0 else 1.0)
             for axis, at, lo, hi in surfaces]
    for (axis, at, lo, hi), n in zip(surfaces, _shares(n_surf, areas)):
        if axis < 2:
            texture = _wall_texture(rng, hi[0])
        elif at == 0.0:
            texture = _floor_texture(rng)
        else:
            texture = _plain_texture(rng, rng.uniform(0.8, 0.95, 3))
        b.plane(axis, at, lo, hi, n, texture)
    # Furniture in a canonical layout, then mirrored in x and/or y per seed.
    fx, fy = rng.random() < 0.5, rng.random() < 0.5
    jitter = rng.uniform(-0.2, 0.2, 4)

    def place(x0: float, y0: float, x1: float, y1: float) -> tuple[float, float, float, float]:
        xs = sorted((w - x0, w - x1)) if fx else [x0, x1]
        ys = sorted((d - y0, d - y1)) if fy else [y0, y1]
        return xs[0], ys[0], xs[1], ys[1]

    wood = rng.uniform([0.35, 0.2, 0.1], [0.6, 0.4, 0.25])
    cab = place(0.0, 2.0 + jitter[0], 0.45, 3.1 + jitter[0])
    sofa = place(1.0 + jitter[1], 0.0, 3.0 + jitter[1], 0.85)
    top = place(2.4 + jitter[2], 3.75, 3.6 + jitter[2], 4.45)
    counts = _shares(n_furn, [6.0, 4.5, 3.0, 2.0])
    b.box((cab[0], cab[1], 0.0), (cab[2], cab[3], 1.8), counts[0], _plain_texture(rng, wood, stripe=0.36))
    fabric = rng.uniform(0.2, 0.7, 3)
    b.box((sofa[0], sofa[1], 0.0), (sofa[2], sofa[3], 0.45), counts[1], _plain_texture(rng, fabric))
    back = (sofa[0], sofa[1], sofa[2], sofa[1] + 0.2) if not fy else (sofa[0], sofa[3] - 0.2, sofa[2], sofa[3])
    b.box((back[0], back[1], 0.45), (back[2], back[3], 0.85), counts[2], _plain_texture(rng, fabric * 0.8))
    b.box((top[0], top[1], 0.73), (top[2], top[3], 0.77), counts[3], _plain_texture(rng, wood * 1.2))
    # Thin structures: four table legs, a lamp pole with a shade.
    legs = _shares(n_thin, [1, 1, 1, 1, 3, 3])
    for (x, y), n in zip([(top[0] + 0.05, top[1] + 0.05), (top[2] - 0.05, top[1] + 0.05),
                          (top[0] + 0.05, top[3] - 0.05), (top[2] - 0.05, top[3] - 0.05)], legs):
        b.rod((x, y, 0.0), 0.73, 0.018, n, wood * 0.7)
    lamp_x, lamp_y = (w - 0.35, d - 0.35) if not (fx and fy) else (0.35, 0.35)
    b.rod((lamp_x, lamp_y, 0.0), 1.55, 0.012, legs[4], np.array([0.15, 0.15, 0.15]))
    shade = _plain_texture(rng, rng.uniform(0.75, 1.0, 3))
    b.box((lamp_x - 0.17, lamp_y - 0.17, 1.45), (lamp_x + 0.17, lamp_y + 0.17, 1.75), legs[5], shade)
    return _to_scene(b, sh_degree)


def make_table(seed: int, centre: tuple[float, float], top: tuple[float, float], height: float,
               num_gaussians: int, sh_degree: int = 0) -> GaussianScene:
    """A table of ``num_gaussians`` Gaussians (metres, z up, standing on z = 0): a 4 cm top of ``top`` (x, y)
    metres centred on ``centre`` (x, y) with its upper face at ``height``, on four thin legs; wood-like
    texture from ``seed``. A support for objects composed into a room (``scenesplat_stereo.build.compose``)."""
    if num_gaussians < 100:
        raise ValueError(f"make_table: num_gaussians must be >= 100, got {num_gaussians}")
    rng = np.random.default_rng(seed)
    b = _Builder(rng)
    (cx, cy), (sx, sy) = centre, top
    lo, hi = (cx - sx / 2, cy - sy / 2), (cx + sx / 2, cy + sy / 2)
    wood = rng.uniform([0.35, 0.2, 0.1], [0.65, 0.45, 0.3])
    n_top, *legs = _shares(num_gaussians, [8, 1, 1, 1, 1])
    b.box((lo[0], lo[1], height - 0.04), (hi[0], hi[1], height), n_top, _plain_texture(rng, wood, stripe=0.12))
    for (x, y), n in zip([(lo[0] + 0.04, lo[1] + 0.04), (hi[0] - 0.04, lo[1] + 0.04), (lo[0] + 0.04, hi[1] - 0.04),
                          (hi[0] - 0.04, hi[1] - 0.04)], legs):
        b.rod((x, y, 0.0), height - 0.04, 0.02, n, wood * 0.6)
    return _to_scene(b, sh_degree)


def _to_scene(b: _Builder, sh_degree: int) -> GaussianScene:
    means, quats, scales, opacities, rgb = (np.concatenate(x) for x in zip(*b.parts))
    n, k = len(means), (sh_degree + 1) ** 2
    sh = np.zeros((n, k, 3))
    sh[:, 0] = (np.clip(rgb, 0.02, 0.95) - 0.5) / SH_C0
    if sh_degree > 0:  # a tinted sheen: per-Gaussian random band coefficients times one tint colour
        tint = b.rng.uniform(0.3, 1.0, 3)
        for band in range(1, sh_degree + 1):
            coeffs = slice(band * band, (band + 1) * (band + 1))
            sh[:, coeffs] = _SH_TINT[band - 1] * b.rng.normal(size=(n, 2 * band + 1, 1)) * tint
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return GaussianScene(means.astype(np.float32), quats.astype(np.float32), scales.astype(np.float32),
                         opacities.astype(np.float32), sh.astype(np.float32), sh_degree)


def room_trajectory(n_frames: int, seed: int = 0, size: tuple[float, float, float] = ROOM_SIZE) -> np.ndarray:
    """A smooth loop of ``n_frames`` OpenCV c2w poses [F, 4, 4] (metres, z-up world of ``make_room``):
    eyes on an ellipse of radii 0.6 x 0.9 m about the room centre at 1.25-1.55 m height, looking
    outwards and slightly down at the walls; the start angle depends on ``seed``."""
    if n_frames < 1:
        raise ValueError(f"room_trajectory: n_frames must be >= 1, got {n_frames}")
    w, d, _ = size
    start = np.random.default_rng(seed).uniform(0, 2 * math.pi)
    a = start + 2 * math.pi * np.arange(n_frames) / n_frames
    eyes = np.column_stack([w / 2 + 0.6 * np.cos(a), d / 2 + 0.9 * np.sin(a), 1.4 + 0.15 * np.sin(2 * a)])
    look = a + 0.5 * math.pi + 0.5 * np.sin(a)
    targets = eyes + np.column_stack([np.cos(look), np.sin(look), np.full(n_frames, -0.25)])
    return look_at(eyes, targets, up=(0.0, 0.0, 1.0))


# ----------------------------------------------------------------------------------------------- files
def write_demo_teachers(out: Path, n_scenes: int = 4, seed: int = 0, num_gaussians: int = DEFAULT_NUM_GAUSSIANS,
                        n_frames: int = 12, width: int = 256, height: int = 192, fov_x_deg: float = 70.0,
                        progress: bool = True) -> list[Path]:
    """Write ``n_scenes`` plain-layout teachers ``out/demo_room_<ii>/`` and return their folders.

    Scene i has SH degree i % 4 and a PSNR drawn inside tier i % 3 of ``protocol.TIERS`` (paper Table 7); ``transforms.json``
    holds ``n_frames`` poses of ``room_trajectory`` at ``width`` x ``height`` pixels (horizontal field of
    view ``fov_x_deg``, principal point at the centre), in OpenGL axes for even i and OpenCV for odd i;
    ``scene.json`` states the convention (for i % 4 == 3 the transforms file states it too). Each scene
    is written in a hidden temporary folder and moved into place, replacing an older one (only one this command
    wrote: ``common.ownership.check_replaceable``, for every room before the first is written).
    """
    out = Path(out)
    for i in range(n_scenes):  # every folder it replaces holds only an earlier run's files, checked before writing
        check_replaceable(out / f"demo_room_{i:02d}", "OUT", OWNER)
    fx = 0.5 * width / math.tan(math.radians(0.5 * fov_x_deg))
    K = intrinsics_matrix(fx, fx, 0.5 * width, 0.5 * height)
    folders = []
    for i in tqdm(range(n_scenes), desc="demo teachers", unit="scene", disable=not progress):
        scene_seed = seed * 1000 + i
        rng = np.random.default_rng([seed, i])
        tier = TIERS[i % len(TIERS)]
        low, high = tier.psnr_low, min(tier.psnr_high, tier.psnr_low + 5.0)  # the open last tier: up to +5 dB
        psnr = round(float(rng.uniform(low + 0.5, high - 0.5)), 2)
        convention = "opencv" if i % 2 else "opengl"
        room = make_room(scene_seed, sh_degree=i % 4, num_gaussians=num_gaussians)
        c2w = room_trajectory(n_frames, seed=scene_seed)
        stored = c2w if convention == "opencv" else c2w @ OPENGL_TO_OPENCV
        transforms = {"camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
                      "w": width, "h": height,
                      "frames": [{"file_path": f"images/frame_{f:05d}.jpg", "transform_matrix": m.tolist()}
                                 for f, m in enumerate(stored)]}
        if i % 4 == 3:
            transforms["camera_convention"] = convention
        final = out / f"demo_room_{i:02d}"
        with StagedFolder(final, OWNER) as tmp:  # replaces an earlier demo room as a whole, or nothing
            save_ply(room, tmp / "point_cloud.ply")
            atomic_write_json(tmp / "transforms.json", transforms, indent=2)
            atomic_write_json(tmp / "scene.json", {"psnr": psnr, "subset": DEMO_SUBSET, "camera_convention": convention,
                                                   "generator": f"scenesplat_stereo.build.demo seed={seed} scene={i}"},
                              indent=2)
        folders.append(final)
    return folders


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", type=Path, help="output folder; one sub-folder per scene")
    p.add_argument("--scenes", type=whole_number("--scenes"), default=4, help="number of scenes (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--gaussians", type=whole_number("--gaussians", MIN_GAUSSIANS),
                   default=DEFAULT_NUM_GAUSSIANS, help=f"Gaussians per room (default {DEFAULT_NUM_GAUSSIANS}, at least "
                   f"{MIN_GAUSSIANS})")
    p.add_argument("--frames", type=whole_number("--frames"), default=12, help="trajectory frames per scene (default 12)")
    p.add_argument("--size", type=argtype(parse_size, "--size"), default="256x192", metavar="WxH",
                   help="native image size in pixels (default 256x192)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    width, height = args.size
    folders = write_demo_teachers(args.out, n_scenes=args.scenes, seed=args.seed, num_gaussians=args.gaussians,
                                  n_frames=args.frames, width=width, height=height, progress=not args.no_progress)
    print(f"wrote {len(folders)} demo teachers to {args.out}")
    return 0
