"""Teacher discovery (SPEC section 3): find 3DGS teacher scenes on disk and return plain records.

Each sub-folder of the root is one teacher in one of three layouts, detected per folder by one small
reader each (nerfstudio dataparser style):

- ``scenesplat`` (SceneSplat-7K / gsplat trainer): ``ckpts/point_cloud_<step>.ply`` (highest step),
  PSNR from ``stats/val_step<step>.json`` key ``psnr`` (the checkpoint's step, else the highest step
  present, with a warning), trajectory ``transforms_train.json`` (else ``transforms.json``).
- ``inria`` (INRIA trainer output): ``point_cloud/iteration_<N>/point_cloud.ply`` (highest N),
  trajectory ``cameras.json``, PSNR from ``results.json`` ``{"ours_<N>": {"PSNR": ...}}`` (the
  checkpoint's N, else the highest present, with a warning) when the file exists.
- ``plain``: ``point_cloud.ply``, else the folder's single scene file in any format ``scene_files.load_scene``
  reads (``.ply``, ``.compressed.ply``, ``.spz``, ``.sog``, ``.splat``, a SOG's ``meta.json`` + WebP images, a
  streamed scene's ``lod-meta.json`` + unit folders, read at its finest level), optional ``transforms.json``.

Any layout may carry ``scene.json`` ``{"psnr": float, "camera_convention": "opencv"|"opengl",
"subset": str, "baseline": metres, "rho": metres}`` (its PSNR counts when the layout has none; ``baseline`` and
``rho``, both > 0, replace the PSNR tier's for this teacher, e.g. a desk-scale scene's 0.06 m). Folders without
these files are grouping folders (e.g. ``ScanNetGS/``), searched up to ``MAX_GROUP_DEPTH`` deep; hidden folders
are skipped. A root that holds a teacher itself is the only one.

Trajectories come out as OpenCV c2w in world units (metres for the paper's tiers; read by ``trajectories``):
``transforms*.json`` (nerfstudio: ``frames[i].transform_matrix`` c2w; ``fl_x fl_y cx cy w h`` or
``camera_angle_x`` at the top level or per frame; cx, cy default to the image centre) is OpenGL unless
the file or ``scene.json`` says ``"camera_convention": "opencv"``; ``cameras.json`` (INRIA:
``position`` = camera centre, ``rotation`` = c2w rotation, OpenCV, ``fx fy width height``, principal
point at the image centre). Frames keep the file's order. A teacher without a trajectory needs an
``OrbitSpec``: its poses circle the median of the Gaussian means, computed when the build loads the
``.ply`` (``resolve_trajectory``), not here.

Subset: ``scene.json`` ``subset``, else the parent folder's name when it is styled like
``ScanNetGS`` / ``ScanNetPPGS-V2`` / ``ReplicaGS`` (``SUBSET_FOLDER_PATTERN``), else ``"default"``.

Every malformed file is a ``Rejection`` naming the file and the field; one bad teacher never stops the
others. Only headers are read here (``scene_files.scene_info``: the ``.ply`` header, a SOG's JSON, ...): a
scene whose data holds NaNs is reported by the build. ``Teacher.ply_path`` is the scene file, whatever its
format.
"""

from __future__ import annotations

import dataclasses
import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from scenesplat_stereo.common.text import format_table, key_safe_name, parse_size
from scenesplat_stereo.scene.cameras import intrinsics_matrix, orbit_poses
from scenesplat_stereo.scene.scene_files import SCENE_JSON, SCENE_SUFFIXES, scene_info
from scenesplat_stereo.scene.trajectories import (TeacherError, finite_number, read_inria_cameras, read_json,
                                                  read_transforms, stack_frames)

Layout = Literal["scenesplat", "inria", "plain"]

SUBSET_FOLDER_PATTERN = re.compile(r"^[A-Za-z0-9]+GS(-V\d+)?$")  # ScanNetGS, ScanNetPPGS-V2, ReplicaGS
DEFAULT_SUBSET = "default"
MAX_GROUP_DEPTH = 3  # teachers root / subset / ... / scene
_MARKERS = ("ckpts", "point_cloud", "scene.json", "cameras.json", "transforms.json", "transforms_train.json")


@dataclass(frozen=True)
class OrbitSpec:
    """A circular trajectory for teachers without one: ``n_frames`` cameras at ``radius`` (world units)
    around the median of the Gaussian means, ``elevation_deg`` above the plane orthogonal to ``up``
    (world direction; the default -y suits COLMAP / INRIA scenes), looking at the median, pinhole with
    horizontal field of view ``fov_x_deg`` at ``width`` x ``height`` pixels (default: ScanNetGS size).
    """

    radius: float
    n_frames: int = 60
    elevation_deg: float = 20.0
    up: tuple[float, float, float] = (0.0, -1.0, 0.0)
    width: int = 616
    height: int = 456
    fov_x_deg: float = 60.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"radius must be a finite number > 0 (world units), got {self.radius}")
        if not (self.n_frames >= 1 and self.width >= 1 and self.height >= 1):
            raise ValueError(f"frames, width and height must be >= 1, got {self.n_frames}, {self.width}x{self.height}")
        if not 0.0 < self.fov_x_deg < 180.0:
            raise ValueError(f"fov must be in (0, 180) degrees, got {self.fov_x_deg}")
        if not -90.0 < self.elevation_deg < 90.0:
            raise ValueError(f"elevation must be in (-90, 90) degrees, got {self.elevation_deg}")

    @classmethod
    def parse(cls, text: str, flag: str = "--orbit") -> OrbitSpec:
        """``"6"`` or ``"radius=6,frames=60,elevation=20,size=616x456,fov=60,up=-y"`` (up: +x -x +y
        -y +z -z). ValueError naming ``flag`` and the bad item."""
        keys = {"radius": "radius", "frames": "n_frames", "elevation": "elevation_deg", "fov": "fov_x_deg"}
        kwargs: dict = {}
        for i, item in enumerate(t.strip() for t in text.split(",") if t.strip()):
            key, sep, value = item.partition("=")
            if not sep and i == 0:
                key, value = "radius", item
            try:
                if key in keys:
                    kwargs[keys[key]] = int(value) if key == "frames" else float(value)
                elif key == "size":
                    kwargs["width"], kwargs["height"] = parse_size(value, "size")
                elif key == "up" and re.fullmatch(r"[+-][xyz]", value):
                    axis = np.eye(3)["xyz".index(value[1])] * (1.0 if value[0] == "+" else -1.0)
                    kwargs["up"] = tuple(float(a) for a in axis)
                else:
                    raise ValueError(f"unknown key or value {item!r}")
            except ValueError as e:
                raise ValueError(f"{flag} {text!r}: {e}") from None
        if "radius" not in kwargs:
            raise ValueError(f"{flag} {text!r}: radius is required")
        try:
            return cls(**kwargs)
        except ValueError as e:
            raise ValueError(f"{flag} {text!r}: {e}") from None

    def intrinsics(self) -> np.ndarray:
        fx = 0.5 * self.width / math.tan(math.radians(0.5 * self.fov_x_deg))
        return intrinsics_matrix(fx, fx, 0.5 * self.width, 0.5 * self.height)


@dataclass
class Teacher:
    """One teacher scene: where its Gaussians are and the trajectory to render it from.

    ``c2w`` [F, 4, 4] OpenCV camera-to-world in world units, frames in the source's order; ``None``
    only for an orbit teacher before ``resolve_trajectory``. ``Ks`` [F, 3, 3] pixels at ``width`` x
    ``height`` (the native resolution). ``camera_convention`` is that of the source files ("opengl" or
    "opencv"; orbits are generated in "opencv"). ``trajectory`` names the source ("transforms.json",
    "cameras.json", ..., or "orbit"). ``baseline`` and ``rho`` (world units) are ``scene.json``'s, None
    when it gives none (the PSNR tier's then apply).
    """

    scene_id: str
    subset: str
    layout: Layout
    ply_path: Path
    psnr: float | None
    c2w: np.ndarray | None
    Ks: np.ndarray
    width: int
    height: int
    sh_degree: int
    camera_convention: str
    frame_names: list[str]
    trajectory: str = ""
    orbit: OrbitSpec | None = None
    baseline: float | None = None
    rho: float | None = None

    @property
    def num_frames(self) -> int:
        return len(self.frame_names)


@dataclass(frozen=True)
class Rejection:
    """A teacher that is not used: ``path`` is the offending file (or folder), ``reason`` names the file
    and the field."""

    scene_id: str
    path: Path
    reason: str
    subset: str = DEFAULT_SUBSET


@dataclass
class Discovery:
    teachers: list[Teacher] = field(default_factory=list)
    rejected: list[Rejection] = field(default_factory=list)


class _Found(NamedTuple):  # what a layout reader finds, before the shared trajectory parsing
    layout: Layout
    ply_path: Path
    psnr: float | None
    trajectory_path: Path | None


def _highest(paths: list[Path], pattern: str) -> tuple[int, Path] | None:
    steps = [(int(m.group(1)), p) for p in paths if (m := re.fullmatch(pattern, p.name))]
    return max(steps, default=None, key=lambda s: s[0])


def _psnr_for_step(candidates: dict[int, Path], step: int, key_of, label: str) -> float | None:
    """PSNR from the candidate file of ``step``, else of the highest step present (with a warning naming
    both steps); None if none."""
    if not candidates:
        return None
    chosen = step if step in candidates else max(candidates)
    path = candidates[chosen]
    if chosen != step:
        warnings.warn(f"{path}: no PSNR for the checkpoint's step {step}; using step {chosen}'s "
                      f"({label.format(step=chosen)})", stacklevel=2)
    value = key_of(read_json(path), chosen)
    if value is None:
        raise TeacherError(path, label.format(step=chosen), "missing")
    return finite_number(value, path, label.format(step=chosen))


# ------------------------------------------------------------------------------------- layout readers
def _read_scenesplat(folder: Path) -> _Found | None:
    ckpts = folder / "ckpts"
    best = _highest(list(ckpts.glob("point_cloud_*.ply")), r"point_cloud_(\d+)\.ply") if ckpts.is_dir() else None
    if best is None:
        return None
    step, ply = best
    stats = {int(m.group(1)): p for p in (folder / "stats").glob("val_step*.json")
             if (m := re.fullmatch(r"val_step(\d+)\.json", p.name))}
    psnr = _psnr_for_step(stats, step, lambda d, s: d.get("psnr") if isinstance(d, dict) else None, "psnr")
    trajectory = next((folder / n for n in ("transforms_train.json", "transforms.json")
                       if (folder / n).is_file()), None)
    return _Found("scenesplat", ply, psnr, trajectory)


def _read_inria(folder: Path) -> _Found | None:
    root = folder / "point_cloud"
    iterations = [p for p in root.glob("iteration_*") if (p / "point_cloud.ply").is_file()] if root.is_dir() else []
    best = _highest(iterations, r"iteration_(\d+)")
    if best is None:
        return None
    step, it_dir = best
    results = folder / "results.json"
    psnr = None
    if results.is_file():
        data = read_json(results)
        keys = {int(m.group(1)): results for k in (data if isinstance(data, dict) else {})
                if (m := re.fullmatch(r"ours_(\d+)", k))}
        if not keys:
            raise TeacherError(results, "ours_<N>", "no entry")
        for k, entry in data.items():
            if re.fullmatch(r"ours_\d+", k) and not isinstance(entry, dict):
                raise TeacherError(results, k, f"expected an object {{\"PSNR\": dB, ...}}, got {entry!r}")
        psnr = _psnr_for_step(keys, step, lambda d, s: d[f"ours_{s}"].get("PSNR"), "ours_{step}.PSNR")
    trajectory = folder / "cameras.json" if (folder / "cameras.json").is_file() else None
    return _Found("inria", it_dir / "point_cloud.ply", psnr, trajectory)


def _scene_files(folder: Path) -> list[Path]:
    """The scene files of a folder: a streamed scene's ``lod-meta.json`` alone when there is one (its units'
    ``meta.json`` sit in sub-folders), else every ``.ply``/``.spz``/``.sog``/``.splat`` and ``meta.json``."""
    if (folder / SCENE_JSON[0]).is_file():
        return [folder / SCENE_JSON[0]]
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                  and (p.suffix in SCENE_SUFFIXES or p.name == SCENE_JSON[1]))


def _read_plain(folder: Path) -> _Found | None:
    plys = _scene_files(folder)
    if not plys:
        return None
    ply = folder / "point_cloud.ply" if (folder / "point_cloud.ply").is_file() else plys[0] if len(plys) == 1 else None
    if ply is None:
        raise TeacherError(folder, "scene file", f"{len(plys)} scene files ({', '.join(p.name for p in plys[:4])}"
                           f"{', ...' if len(plys) > 4 else ''}) and none named point_cloud.ply")
    trajectory = folder / "transforms.json" if (folder / "transforms.json").is_file() else None
    return _Found("plain", ply, None, trajectory)


_LAYOUT_READERS = (_read_scenesplat, _read_inria, _read_plain)


# ------------------------------------------------------------------------------------------ discovery
def _scene_json(folder: Path) -> dict:
    path = folder / "scene.json"
    if not path.is_file():
        return {}
    data = read_json(path)
    if not isinstance(data, dict):
        raise TeacherError(path, "file", "expected a JSON object")
    if data.get("psnr") is not None:
        finite_number(data["psnr"], path, "psnr")
    for key in ("baseline", "rho"):
        if data.get(key) is not None:
            finite_number(data[key], path, key, positive=True)
    conv = data.get("camera_convention")
    if conv not in (None, "opencv", "opengl"):
        raise TeacherError(path, "camera_convention", f"expected 'opencv' or 'opengl', got {conv!r}")
    subset = data.get("subset")
    if subset is not None and (not isinstance(subset, str) or not subset.strip() or "/" in subset):
        raise TeacherError(path, "subset", f"expected a non-empty name, got {subset!r}")
    return data


def _subset_from_folder(folder: Path) -> str:
    parent = folder.resolve().parent.name
    return parent if SUBSET_FOLDER_PATTERN.match(parent) else DEFAULT_SUBSET


def _read_teacher(folder: Path, scene_id: str, orbit: OrbitSpec | None) -> Teacher:
    meta = _scene_json(folder)
    found = next((f for reader in _LAYOUT_READERS if (f := reader(folder)) is not None), None)
    if found is None:
        raise TeacherError(folder, "layout", "no teacher scene (expected ckpts/point_cloud_<step>.ply, "
                           "point_cloud/iteration_<N>/point_cloud.ply, point_cloud.ply or one scene file)")
    try:
        num_gaussians, sh_degree = scene_info(found.ply_path)
    except ValueError as e:
        raise TeacherError(found.ply_path, "header", str(e).removeprefix(f"{found.ply_path}: ")) from None
    if num_gaussians == 0:
        raise TeacherError(found.ply_path, "element vertex", "zero Gaussians")
    psnr = found.psnr if found.psnr is not None else (float(meta["psnr"]) if meta.get("psnr") is not None else None)
    subset = meta.get("subset") or _subset_from_folder(folder)
    common = dict(scene_id=scene_id, subset=subset, layout=found.layout, ply_path=found.ply_path,
                  psnr=psnr, sh_degree=sh_degree,
                  **{k: float(meta[k]) for k in ("baseline", "rho") if meta.get(k) is not None})
    if found.trajectory_path is None:
        if orbit is None:
            raise TeacherError(folder, "trajectory", "no transforms.json / transforms_train.json / "
                               "cameras.json; give an orbit (--orbit) to render it")
        return _orbit_teacher(common, orbit)
    path = found.trajectory_path
    reader = read_inria_cameras if path.name == "cameras.json" else read_transforms
    frames, convention = reader(path, meta.get("camera_convention"))
    c2w, Ks, (width, height), names = stack_frames(frames, path)
    return Teacher(**common, c2w=c2w, Ks=Ks, width=width, height=height, camera_convention=convention,
                   frame_names=names, trajectory=path.name)


def _orbit_teacher(common: dict, orbit: OrbitSpec) -> Teacher:
    return Teacher(**common, c2w=None, Ks=np.repeat(orbit.intrinsics()[None], orbit.n_frames, axis=0),
                   width=orbit.width, height=orbit.height, camera_convention="opencv", trajectory="orbit",
                   frame_names=[f"orbit_{i:06d}" for i in range(orbit.n_frames)], orbit=orbit)


def scene_file_teacher(path: Path, orbit: OrbitSpec) -> Teacher:
    """A teacher of one scene file (any format of ``scene_files.load_scene``; a ``meta.json`` or
    ``lod-meta.json`` stands for its folder), rendered along ``orbit``; named after the file (its folder for
    the JSON files). ``ValueError`` naming the file when it is not a readable scene."""
    path = Path(path)
    num_gaussians, sh_degree = scene_info(path)
    if num_gaussians == 0:
        raise ValueError(f"{path}: zero Gaussians")
    name = path.resolve().parent.name if path.name in SCENE_JSON else path.name.split(".")[0]
    return _orbit_teacher(dict(scene_id=key_safe_name(name or "scene"), subset=DEFAULT_SUBSET, layout="plain",
                               ply_path=path.resolve(), psnr=None, sh_degree=sh_degree), orbit)


def _looks_like_teacher(folder: Path) -> bool:
    return any((folder / m).exists() for m in _MARKERS) or bool(_scene_files(folder))


def _teacher_folders(root: Path) -> list[Path]:
    """Teacher folders under root (sorted, depth-first); leaf folders that hold nothing are returned
    too, so that they are reported."""
    if _looks_like_teacher(root):
        return [root]
    out: list[Path] = []

    def walk(folder: Path, depth: int) -> None:
        for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
            has_subdirs = any(p.is_dir() and not p.name.startswith(".") for p in sub.iterdir())
            if _looks_like_teacher(sub) or not has_subdirs or depth == MAX_GROUP_DEPTH:
                out.append(sub)
            else:
                walk(sub, depth + 1)

    walk(root, 1)
    return out


def discover_teachers(root: Path, orbit: OrbitSpec | None = None) -> Discovery:
    """Find every teacher under ``root`` (see the module docstring). ``orbit`` gives a trajectory to
    teachers that have none; without it they are rejected. Scene ids are folder names made
    usable in sample keys (``text.key_safe_name``: '.', '/', whitespace and '__' become '_', with a
    warning); a duplicate id is rejected."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"teachers root {root} is not a folder")
    found = Discovery()
    seen: dict[str, Path] = {}
    renamed = 0
    for folder in _teacher_folders(root):
        name = folder.resolve().name
        subset = _subset_from_folder(folder)
        try:
            try:
                scene_id = key_safe_name(name)
            except ValueError as e:
                scene_id = name
                raise TeacherError(folder, "folder name", str(e)) from None
            renamed += scene_id != name
            if scene_id in seen:
                raise TeacherError(folder, "scene id", f"duplicate of {seen[scene_id]}")
            teacher = _read_teacher(folder, scene_id, orbit)
        except TeacherError as e:
            found.rejected.append(Rejection(scene_id, e.path, str(e), subset))
            continue
        seen[scene_id] = folder
        found.teachers.append(teacher)
    if renamed:
        warnings.warn(f"{root}: {renamed} scene folder names contain '.', '/', whitespace or '__', replaced by "
                      "'_' in scene ids", stacklevel=2)
    return found


def resolve_trajectory(teacher: Teacher, means: np.ndarray) -> Teacher:
    """The teacher with its trajectory: orbit teachers get poses around the median of ``means`` [N, 3]
    (world units, the loaded Gaussians); others are returned unchanged."""
    if teacher.c2w is not None:
        return teacher
    means = np.asarray(means, dtype=np.float64)
    if means.ndim != 2 or means.shape[1] != 3 or len(means) == 0 or not np.isfinite(means).all():
        raise ValueError(f"{teacher.ply_path}: means: need finite [N, 3] positions to place the orbit, "
                         f"got shape {means.shape}")
    o = teacher.orbit
    assert o is not None, "a teacher without c2w is an orbit teacher"
    c2w = orbit_poses(np.median(means, axis=0), o.radius, o.n_frames, o.elevation_deg, o.up)
    return dataclasses.replace(teacher, c2w=c2w)


def summary_table(discovery: Discovery, dropped: list[Rejection] = (), per_teacher: bool = False) -> str:
    """Text table per subset: teacher folders found, kept (readable and not in ``dropped``, e.g. by the
    PSNR filter) and dropped (rejected at discovery or in ``dropped``), then each drop with its reason;
    with ``per_teacher`` one line per kept teacher (layout, frames, size, SH degree, PSNR, source)."""
    dropped_ids = {r.scene_id for r in dropped}
    kept = [t for t in discovery.teachers if t.scene_id not in dropped_ids]
    drops = list(discovery.rejected) + list(dropped)
    found = [*discovery.teachers, *discovery.rejected]
    rows = [("subset", "found", "kept", "dropped")]
    for s in sorted({x.subset for x in found}) + ["total"]:
        rows.append((s, *(str(sum(s in ("total", x.subset) for x in group)) for group in (found, kept, drops))))
    lines = [format_table(rows)]
    if per_teacher and kept:
        lines += ["", "kept teachers:", format_table(
            [("scene", "subset", "layout", "frames", "size", "SH", "PSNR", "trajectory")]
            + [(t.scene_id, t.subset, t.layout, str(t.num_frames), f"{t.width}x{t.height}", str(t.sh_degree),
                "-" if t.psnr is None else f"{t.psnr:.2f}", f"{t.trajectory} ({t.camera_convention})")
               for t in kept])]
    if drops:
        lines += ["", f"dropped ({len(drops)}):"] + [f"  {r.scene_id} [{r.subset}] {r.reason}  ({r.path})"
                                                      for r in drops]
    return "\n".join(lines)

