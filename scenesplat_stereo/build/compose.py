"""Real captures composed into procedural rooms: plain-layout teachers at the sizes and depths users shoot
(``scenesplat-stereo compose-teachers``).

Why: a captured object rendered alone sits in a void, and at its capture's arbitrary units; a model trained on
such renders learns the void and the wrong depths. Here each capture (any format ``scene_files.load_scene``
reads) is measured, turned upright, scaled to metres and put in a room of ``demo.make_room`` (z up, metres),
and the cameras circle it at the distances of one scale family (``FAMILIES``):

- the object: Gaussians with opacity below ``MIN_OPACITY`` and those farther from the opacity-weighted median
  than ``OUTLIER_FACTOR`` times the weighted 90th percentile of the distances are floaters and are dropped; the
  object's bounds are the opacity-weighted ``BOUNDS_PERCENTILES`` of the rest per axis (numpy's
  ``inverted_cdf`` with weights), and Gaussians beyond the bounds by more than ``KEEP_MARGIN`` of the largest
  side are dropped too. Its size is the bounds' largest side.
- upright: the capture's up axis (``--up``, ``-y`` for COLMAP / INRIA captures) becomes +z by a fixed rotation,
  then a random turn about z; ``transform.transform_scene`` turns the quaternions and the SH bands with it and
  adds log(k) to the log-scales.
- placed: scaled to a metric size drawn from the family, centred on the room's centre, its lower bound on the
  floor (``statue``) or on a desk-sized table top (``tabletop``, ``demo.make_table``, ``DESK_TOP``); the room
  grows so that every camera fits (its Gaussian count grows with its surface).
- cameras (OpenCV c2w, metres): a full orbit at a distance to the object's centre that swings between two
  values drawn inside the family's range (the near one in its nearest quarter, the far one in its farther half;
  never nearer than ``NEAREST`` times the object's size), at 5-35 degrees elevation, looking at the object with
  the room behind it; every ``PAST_EVERY``-th frame turns 50-80 degrees aside and looks past the object into
  the room. Horizontal field of view 60-75 degrees.
- ``scene.json``: subset ``captures-in-rooms``, a PSNR label inside the family's tier (the object is a real
  capture; its quality is not measured here), the family's stereo ``baseline`` and target radius ``rho`` (at
  most 0.4 times the nearest camera distance; metres, read by ``teachers`` and used by ``protocol.plan_scene``
  before the tier's), and where it came from.

Everything is deterministic for a seed. Every capture is read and measured before anything is written; OUT is
replaced as a whole (``common.ownership.StagedFolder``).
"""

from __future__ import annotations

import argparse
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenesplat_stereo.build.demo import (
    DEFAULT_NUM_GAUSSIANS,
    ROOM_SIZE,
    make_room,
    make_table,
)
from scenesplat_stereo.common.files import atomic_write_json
from scenesplat_stereo.common.ownership import StagedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import (
    argtype,
    key_safe_name,
    parse_size,
    whole_number,
)
from scenesplat_stereo.scene.cameras import intrinsics_matrix, look_at
from scenesplat_stereo.scene.gaussians import ARRAYS, GaussianScene, save_ply
from scenesplat_stereo.scene.ply import PlyRepairWarning
from scenesplat_stereo.scene.scene_files import load_scene
from scenesplat_stereo.scene.transform import transform_scene

OWNER = "scenesplat-stereo compose-teachers"
SUBSET = "captures-in-rooms"
SCENE_SUFFIXES = (".ply", ".spz", ".sog", ".splat")  # files a --captures folder is searched for
MIN_OPACITY = 0.1  # below: a floater (nearly invisible; often the haze around a capture)
OUTLIER_FACTOR = 3.0  # x the weighted 90th percentile distance to the weighted median
BOUNDS_PERCENTILES = (1.0, 99.0)  # opacity-weighted, per axis
KEEP_MARGIN = 0.1  # of the largest side: Gaussians beyond the bounds by more are dropped
PAST_EVERY = 4  # every 4th frame looks past the object into the room
DESK_TOP = ((1.0, 1.6), (0.6, 0.9))  # m, the table top's x and y ranges (at least the object's footprint + 0.3 m)
ROOM_MARGIN = 0.9  # m between the widest orbit and a wall (clear of the room's furniture)
NEAREST = 0.75  # x the object's size: the nearest camera distance to its centre (it then fills about 67 deg)
ELEVATION_DEG = (5.0, 35.0)
FOV_X_DEG = (60.0, 75.0)
UP_AXES = {f"{s}{a}": np.eye(3)[i] * (1.0 if s == "+" else -1.0) for i, a in enumerate("xyz") for s in "+-"}


@dataclass(frozen=True)
class ScaleFamily:
    """Where an object of this kind is shot: its largest side ``size`` (m) and the camera's distance to its
    centre (m), both ranges; what it stands on; the PSNR label range (dB, inside one tier of
    ``protocol.TIERS``), the stereo baseline and target radius (m) its teachers get."""

    name: str
    size: tuple[float, float]
    distance: tuple[float, float]
    support: str  # "table" or "floor"
    psnr: tuple[float, float]
    baseline: float
    rho: float


FAMILIES = {f.name: f for f in (
    ScaleFamily("tabletop", (0.15, 0.6), (0.25, 1.5), "table", (31.0, 34.5), 0.063, 0.10),
    ScaleFamily("statue", (1.0, 2.0), (1.5, 5.0), "floor", (35.5, 39.5), 0.10, 0.20),
)}


@dataclass(frozen=True)
class Capture:
    """A capture measured: ``scene`` upright (``upright`` [3, 3] applied: z up, capture units), floaters
    dropped; ``lo``, ``hi`` [3] the object's percentile bounds in that frame; ``dropped`` Gaussians removed."""

    path: Path
    upright: np.ndarray
    scene: GaussianScene
    lo: np.ndarray
    hi: np.ndarray
    dropped: int

    @property
    def size(self) -> float:
        return float(np.max(self.hi - self.lo))


@dataclass
class Composed:
    """One composed teacher: ``scene`` (metres, z up: room, support, then the object's rows ``object_rows``);
    the object's bounds centre ``centre`` [3] and largest side ``size`` (m); capture -> world as
    ``scale`` R p + ``offset`` (R includes the upright turn); cameras ``c2w`` [F, 4, 4] OpenCV, ``looks_at`` [F]
    (False for the frames that look past the object), one ``K`` at ``width`` x ``height``."""

    scene: GaussianScene
    object_rows: slice
    centre: np.ndarray
    size: float
    scale: float
    R: np.ndarray
    offset: np.ndarray
    distance: tuple[float, float]
    c2w: np.ndarray
    looks_at: np.ndarray
    K: np.ndarray
    width: int
    height: int
    room_size: tuple[float, float, float]


def upright_rotation(up: str) -> np.ndarray:
    """The rotation taking the capture's ``up`` axis ("+x" ... "-z") to +z (rows: a, up x a, up)."""
    if up not in UP_AXES:
        raise ValueError(f"--up {up!r}: expected one of {', '.join(UP_AXES)}")
    u = UP_AXES[up]
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    return np.stack([a, np.cross(u, a), u])


def _weighted_percentile(x: np.ndarray, w: np.ndarray, q: float) -> np.ndarray:
    return np.percentile(x, q, axis=0, weights=w, method="inverted_cdf")


def measure_capture(scene: GaussianScene, path: Path, up: str = "-y") -> Capture:
    """The capture upright with its floaters dropped and its bounds (see the module docstring); ValueError
    naming ``path`` when nothing is left or the extent is not a finite positive size."""
    R0 = upright_rotation(up)
    upright = transform_scene(scene, R0)
    m, o = upright.means.astype(np.float64), upright.opacities.astype(np.float64)
    keep = o >= MIN_OPACITY
    if not keep.any():
        raise ValueError(f"{path}: no Gaussian left after dropping floaters (opacity < {MIN_OPACITY})")
    centre = _weighted_percentile(m[keep], o[keep], 50.0)
    dist = np.linalg.norm(m - centre, axis=1)
    keep &= dist <= OUTLIER_FACTOR * _weighted_percentile(dist[keep], o[keep], 90.0)
    lo, hi = (_weighted_percentile(m[keep], o[keep], q) for q in BOUNDS_PERCENTILES)
    size = float(np.max(hi - lo))
    if not (math.isfinite(size) and size > 0):
        raise ValueError(f"{path}: object extent {size} is not a finite size > 0 ({int(keep.sum())} Gaussians "
                         "after dropping floaters)")
    margin = KEEP_MARGIN * size
    keep &= ((m >= lo - margin) & (m <= hi + margin)).all(axis=1)
    return Capture(path, R0, upright.subset(keep), lo, hi, len(scene) - int(keep.sum()))


def read_capture(path: Path, up: str = "-y") -> Capture:
    """Read (``load_scene``: by the file's first bytes) and measure one capture; a row with NaN or infinite
    attributes is refused, not repaired: ValueError naming the file."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", PlyRepairWarning)
        try:
            scene = load_scene(path)
        except PlyRepairWarning as e:  # "<path>: k of N Gaussians have bad rows: ...; those rows were dropped"
            detail = str(e).removeprefix(f"{path}: ").split(";")[0]
            raise ValueError(f"{path}: {detail}; a capture is refused, not repaired") from None
    if len(scene) == 0:
        raise ValueError(f"{path}: zero Gaussians")
    return measure_capture(scene, path, up)


def _merge(scenes: list[GaussianScene]) -> GaussianScene:
    return GaussianScene(*(np.concatenate([getattr(s, k) for s in scenes])
                           for k in ARRAYS), scenes[0].sh_degree)


def orbit_frames(centre: np.ndarray, distance: tuple[float, float], n_frames: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(c2w [F, 4, 4] OpenCV, looks_at [F] bool): a full orbit about ``centre`` (z up, metres) whose distance to
    it swings twice between ``distance`` (lo, hi), elevation within ``ELEVATION_DEG``; the frames that do not
    look at the centre turn 50-80 degrees aside about z."""
    f = np.arange(n_frames) / n_frames
    a = rng.uniform(0, 2 * math.pi) + 2 * math.pi * f
    r = distance[0] + (distance[1] - distance[0]) * (0.5 - 0.5 * np.cos(4 * math.pi * f + rng.uniform(0, 2 * math.pi)))
    el = np.radians(ELEVATION_DEG[0] + (ELEVATION_DEG[1] - ELEVATION_DEG[0])
                    * (0.5 + 0.5 * np.sin(6 * math.pi * f + rng.uniform(0, 2 * math.pi))))
    eyes = centre + r[:, None] * np.column_stack([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
    looks = np.arange(n_frames) % PAST_EVERY != PAST_EVERY - 1
    view = centre - eyes
    turn = np.radians(rng.uniform(50, 80, n_frames)) * rng.choice([-1.0, 1.0], n_frames) * ~looks
    view = np.column_stack([np.cos(turn) * view[:, 0] - np.sin(turn) * view[:, 1],
                            np.sin(turn) * view[:, 0] + np.cos(turn) * view[:, 1], view[:, 2]])
    return look_at(eyes, eyes + view, up=(0.0, 0.0, 1.0)), looks


def compose_teacher(capture: Capture, family: ScaleFamily, rng: np.random.Generator, n_frames: int = 24,
                    size_px: tuple[int, int] = (256, 192), room_gaussians: int = DEFAULT_NUM_GAUSSIANS) -> Composed:
    """One teacher: ``capture`` at a size of ``family`` in a room sized to the orbit (module docstring)."""
    size = float(rng.uniform(*family.size))
    d_lo, d_hi = max(family.distance[0], NEAREST * size), family.distance[1]
    span = d_hi - d_lo
    distance = (d_lo + 0.25 * span * float(rng.uniform()), d_hi - 0.5 * span * float(rng.uniform()))
    k = size / capture.size
    yaw = rng.uniform(0, 2 * math.pi)
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    extent = k * (capture.hi - capture.lo)
    support = float(rng.uniform(0.70, 0.78)) if family.support == "table" else 0.0
    top_z = support + extent[2]
    max_eye_z = support + 0.5 * extent[2] + distance[1] * math.sin(math.radians(ELEVATION_DEG[1]))
    w, d = (max(s, 2 * (distance[1] + ROOM_MARGIN)) for s in ROOM_SIZE[:2])
    h = max(ROOM_SIZE[2], max_eye_z + 0.4, top_z + 0.4)
    area = lambda x, y, z: 2 * (x * y + x * z + y * z)
    n_room = max(2000, round(room_gaussians * area(w, d, h) / area(*ROOM_SIZE)))
    seed = int(rng.integers(2**31))
    parts = [make_room(seed, capture.scene.sh_degree, n_room, (w, d, h))]
    if family.support == "table":
        footprint = np.abs(Rz[:2, :2]) @ extent[:2]  # the turned bounds' axis-aligned footprint
        top = (max(rng.uniform(*DESK_TOP[0]), footprint[0] + 0.3), max(rng.uniform(*DESK_TOP[1]), footprint[1] + 0.3))
        parts.append(make_table(seed + 1, (w / 2, d / 2), top, support, max(200, room_gaussians // 20),
                                capture.scene.sh_degree))
    mid = 0.5 * (capture.lo + capture.hi)
    offset = np.array([w / 2, d / 2, support]) - k * (Rz @ np.array([mid[0], mid[1], capture.lo[2]]))
    obj = transform_scene(capture.scene, Rz, k, offset)
    start = sum(len(p) for p in parts)
    centre = np.array([w / 2, d / 2, support + 0.5 * extent[2]])
    c2w, looks = orbit_frames(centre, distance, n_frames, rng)
    fx = 0.5 * size_px[0] / math.tan(math.radians(0.5 * rng.uniform(*FOV_X_DEG)))
    return Composed(_merge(parts + [obj]), slice(start, start + len(obj)), centre, size, k, Rz @ capture.upright, offset,
                    distance,
                    c2w, looks, intrinsics_matrix(fx, fx, 0.5 * size_px[0], 0.5 * size_px[1]), size_px[0],
                    size_px[1], (w, d, h))


def _write_teacher(folder: Path, c: Composed, family: ScaleFamily, capture: Capture, psnr: float, note: str) -> None:
    folder.mkdir()
    save_ply(c.scene, folder / "point_cloud.ply", durable=False)
    K = c.K
    atomic_write_json(folder / "transforms.json", {
        "camera_model": "OPENCV", "camera_convention": "opencv", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2],
        "cy": K[1, 2], "w": c.width, "h": c.height,
        "frames": [{"file_path": f"images/frame_{f:05d}.jpg", "transform_matrix": m.tolist(),
                    "looks_at_object": bool(look)} for f, (m, look) in enumerate(zip(c.c2w, c.looks_at))]}, indent=2)
    atomic_write_json(folder / "scene.json", {
        "psnr": psnr, "subset": SUBSET, "camera_convention": "opencv", "baseline": family.baseline,
        "rho": min(family.rho, 0.4 * c.distance[0]), "scale_family": family.name, "object_size_m": round(c.size, 4),
        "distance_m": [round(x, 4) for x in c.distance], "capture": capture.path.name,
        "room_size_m": [round(x, 3) for x in c.room_size], "generator": note}, indent=2)


def capture_files(given: list[Path]) -> list[Path]:
    """The scene files named by ``--captures``: files as given, folders searched (not hidden parts) for
    ``SCENE_SUFFIXES``, sorted; ValueError naming the flag for a missing path or a folder with none."""
    files: list[Path] = []
    for p in given:
        if p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in SCENE_SUFFIXES
                           and not any(part.startswith(".") for part in f.relative_to(p).parts))
            if not found:
                raise ValueError(f"--captures {p}: no scene files ({' '.join(SCENE_SUFFIXES)})")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise ValueError(f"--captures {p}: no such file or folder")
    return files


def _capture_name(path: Path) -> str:
    """A capture's name: its file name before the first dot, or its folder's name for ``point_cloud.*``."""
    stem = path.name.split(".")[0]
    return path.resolve().parent.name if stem == "point_cloud" else stem


def write_composed_teachers(out: Path, captures: list[Capture], families: list[str], rooms: int = 2, seed: int = 0,
                            n_frames: int = 24, size_px: tuple[int, int] = (256, 192),
                            room_gaussians: int = DEFAULT_NUM_GAUSSIANS, progress: bool = True) -> list[str]:
    """Write ``rooms`` teachers per capture (teacher j of a capture in family ``families[j % len]``) to ``out``,
    replacing it as a whole; returns the teacher folder names (``<capture>_<family>_<jj>``, ``_capture_name``)."""
    names = [key_safe_name(_capture_name(c.path)) for c in captures]
    if len(set(names)) < len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"--captures: two captures are named {dup!r} ({', '.join(str(c.path) for c, n in zip(captures, names) if n == dup)})")
    written = []
    with StagedFolder(out, OWNER) as tmp:
        jobs = [(ci, j) for ci in range(len(captures)) for j in range(rooms)]
        for ci, j in tqdm(jobs, desc="composed teachers", unit="teacher", disable=not progress):
            family = FAMILIES[families[j % len(families)]]
            rng = np.random.default_rng([seed, ci, j])
            composed = compose_teacher(captures[ci], family, rng, n_frames, size_px, room_gaussians)
            psnr = round(float(rng.uniform(*family.psnr)), 2)
            name = f"{names[ci]}_{family.name}_{j:02d}"
            _write_teacher(tmp / name, composed, family, captures[ci], psnr,
                           f"scenesplat_stereo.build.compose seed={seed} capture={ci} room={j}")
            written.append(name)
    return written


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--captures", type=Path, nargs="+", required=True, metavar="PATH",
                   help=f"capture files or folders searched for {' '.join(SCENE_SUFFIXES)} (read by their first bytes)")
    p.add_argument("--out", type=Path, required=True, help="teachers folder, replaced as a whole (one sub-folder per teacher)")
    p.add_argument("--rooms", type=whole_number("--rooms"), default=2, help="teachers (rooms) per capture (default 2)")
    p.add_argument("--scales", type=argtype(_parse_families, "--scales"), default="tabletop,statue",
                   help=f"scale families, used in turn per capture: {', '.join(FAMILIES)} (default %(default)s)")
    p.add_argument("--up", default="-y", choices=sorted(UP_AXES), help="the captures' up axis (default -y: COLMAP / INRIA)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--frames", type=whole_number("--frames"), default=24, help="trajectory frames per teacher (default 24)")
    p.add_argument("--size", type=argtype(parse_size, "--size"), default="256x192", metavar="WxH",
                   help="native image size in pixels (default 256x192)")
    p.add_argument("--gaussians", type=whole_number("--gaussians"), default=DEFAULT_NUM_GAUSSIANS,
                   help=f"Gaussians of a room of the default size (4 x 5 x 2.6 m), more for larger ones (default "
                        f"{DEFAULT_NUM_GAUSSIANS}; at least 2000)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _parse_families(text: str, flag: str = "--scales") -> list[str]:
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [n for n in names if n not in FAMILIES]
    if not names or bad:
        raise ValueError(f"{flag} {text!r}: expected a comma list of {', '.join(FAMILIES)}")
    return names


def run(args: argparse.Namespace) -> int:
    """CLI entry: every input is read and measured before OUT is touched; a bad one is a ValueError naming it."""
    check_replaceable(args.out, "--out", OWNER)
    files = capture_files(args.captures)
    check_apart(args.out, "--out", {"--captures": list(args.captures)}, replaced=True)
    captures = [read_capture(f, args.up) for f in files]
    names = write_composed_teachers(args.out, captures, args.scales, args.rooms, args.seed, args.frames, args.size,
                                    args.gaussians, progress=not args.no_progress)
    for c in captures:
        print(f"{c.path}: {len(c.scene):,} Gaussians kept, {c.dropped:,} floaters dropped, SH {c.scene.sh_degree}")
    print(f"wrote {len(names)} composed teachers to {args.out}")
    return 0
