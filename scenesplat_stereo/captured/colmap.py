"""Camera pose recovery for an ordered image sequence with COLMAP (pycolmap 4.x), intrinsics held fixed.

Generic: nothing here knows about IRS. Given the images of one sequence (in capture order) and one pinhole
camera, it runs SIFT feature extraction (CPU; GPU when pycolmap has CUDA), feature matching (exhaustive
for short sequences, sequential otherwise, with loop detection only when a local vocabulary-tree file is
given: it cannot be downloaded at run time), and incremental mapping with the intrinsics fixed (no focal,
principal-point or distortion refinement), and keeps the largest reconstruction (most registered images).

Conventions: poses are returned as c2w 4x4 in OpenCV axes (x right, y down, z forward) in the
reconstruction's arbitrary units (COLMAP has no scale); the caller scales them. Pixel coordinates follow
COLMAP, which is the SPEC section 1 convention: pixel (u, v) covers [u, u+1) x [v, v+1), the centre of the
top-left pixel is (0.5, 0.5).

pycolmap is a regular dependency, imported when a function needs it (``import_pycolmap`` turns a failed
import into a ``NotAvailable`` that says how to install it).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from scenesplat_stereo.common.commandline import NotAvailable

# Matching strategy: exhaustive up to this many frames (all n(n-1)/2 pairs: robust, but O(n^2)), sequential
# above (about 14 pairs per frame with the overlap below). Measured at 960x540 with 8192 SIFT features on a
# 2-core CPU, exhaustive matching of 50 frames took 2x the time of sequential matching of 100 (docs/irs.md).
EXHAUSTIVE_MAX_FRAMES = 40
# Sequential matching: each image is matched with this many following images (COLMAP's default).
SEQUENTIAL_OVERLAP = 10
MATCHING_MODES = ("auto", "exhaustive", "sequential")


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera in pixels (COLMAP model PINHOLE): focal lengths, principal point, image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsics matrix, float64, pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> PinholeCamera:
        """The same camera for the image resized to ``width`` x ``height`` (SPEC section 1 pixel
        convention: coordinates scale about the image corner, see ``cameras.scale_intrinsics``)."""
        from scenesplat_stereo.scene.cameras import scale_intrinsics

        K = scale_intrinsics(self.K, (self.width, self.height), (width, height))
        return PinholeCamera(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    @classmethod
    def parse(cls, text: str, width: int, height: int) -> PinholeCamera:
        """From ``"fx,fy,cx,cy"`` (pixels) and the image size; raises ValueError on a malformed string."""
        parts = [p for p in text.replace(" ", "").split(",") if p]
        if len(parts) != 4:
            raise ValueError(f"intrinsics must be 'fx,fy,cx,cy' in pixels, got {text!r}")
        try:
            fx, fy, cx, cy = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"intrinsics must be 4 numbers 'fx,fy,cx,cy' in pixels, got {text!r}") from None
        if not (fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()):
            raise ValueError(f"intrinsics must be finite with fx, fy > 0, got {text!r}")
        return cls(fx, fy, cx, cy, int(width), int(height))


@dataclass
class RecoveryOptions:
    """Knobs of :func:`recover_poses`. Defaults are COLMAP's except where the docstring says otherwise.

    matching: "auto" (exhaustive up to ``exhaustive_max_frames`` frames, else sequential), "exhaustive"
    or "sequential". vocab_tree_path: a local COLMAP vocabulary-tree file; when given, sequential matching
    adds loop detection (without it there is none: the file cannot be downloaded at run time).
    max_num_features: SIFT features per image. init_min_num_inliers: inliers needed by the initial pair
    (lower it for small images). num_threads: -1 = all cores. seed: COLMAP's random seed (results are
    reproducible for a fixed seed and thread count). verbose: keep COLMAP's INFO log on stderr.
    """

    matching: str = "auto"
    exhaustive_max_frames: int = EXHAUSTIVE_MAX_FRAMES
    sequential_overlap: int = SEQUENTIAL_OVERLAP
    vocab_tree_path: Path | None = None
    max_num_features: int = 8192
    init_min_num_inliers: int = 100
    num_threads: int = -1
    seed: int = 0
    verbose: bool = False

    def matching_for(self, n_frames: int) -> str:
        """The matching actually used for ``n_frames`` images (checks the options: ValueError for an
        unknown mode, FileNotFoundError for a missing vocabulary tree)."""
        if self.matching not in MATCHING_MODES:
            raise ValueError(f"matching must be one of {MATCHING_MODES}, got {self.matching!r}")
        if self.vocab_tree_path is not None and not Path(self.vocab_tree_path).is_file():
            raise FileNotFoundError(f"vocab_tree_path: {self.vocab_tree_path} is not a file (loop detection "
                                    "needs a local COLMAP vocabulary tree; none is downloaded)")
        if self.matching != "auto":
            return self.matching
        return "exhaustive" if n_frames <= self.exhaustive_max_frames else "sequential"


@dataclass
class Observations:
    """Sparse points seen by one registered image: pixel positions ``xy [M,2]`` (COLMAP pixel convention,
    float64), depth along the camera's z axis ``depth [M]`` (reconstruction units) and ``point_ids [M]``."""

    xy: np.ndarray
    depth: np.ndarray
    point_ids: np.ndarray


@dataclass
class Recovery:
    """The largest reconstruction of one sequence.

    indices: positions (into the input list) of the registered images, increasing. c2w: [R,4,4] float64,
    OpenCV axes, reconstruction units, in the order of ``indices``. observations: one per registered image.
    mean_reprojection_error: pixels (NaN when nothing is registered). num_models: reconstructions COLMAP
    produced (only the largest is kept). matching: the matching used.
    """

    num_input: int
    indices: list[int]
    c2w: np.ndarray
    observations: list[Observations]
    mean_reprojection_error: float
    num_points3D: int
    num_models: int
    matching: str
    camera_params: list[float] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)  # wall time of extract / match / map

    @property
    def registered(self) -> int:
        return len(self.indices)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file from its header (OpenImageIO); ValueError naming the file if
    it cannot be opened."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: cannot open image ({oiio.geterror()})")
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def _stage_images(image_paths: Sequence[Path], stage: Path) -> list[str]:
    """Link the images into ``stage`` as 000000.ext, 000001.ext, ... so that COLMAP's name order (used by
    sequential matching) is the input order whatever the original names (l_2.png sorts after l_10.png)."""
    stage.mkdir(parents=True, exist_ok=True)
    names = []
    for i, p in enumerate(image_paths):
        name = f"{i:06d}{Path(p).suffix.lower()}"
        link = stage / name
        if link.is_symlink() or link.exists():
            link.unlink()
        os.symlink(Path(p).resolve(), link)
        names.append(name)
    return names


def _camera_params(camera: PinholeCamera) -> str:
    return ",".join(repr(float(v)) for v in (camera.fx, camera.fy, camera.cx, camera.cy))


def _mapping_options(pycolmap: Any, options: RecoveryOptions) -> Any:
    """Incremental mapping with the intrinsics held fixed (no focal, principal point or extra refinement)."""
    po = pycolmap.IncrementalPipelineOptions()
    po.ba_refine_focal_length = False
    po.ba_refine_principal_point = False
    po.ba_refine_extra_params = False
    po.mapper.abs_pose_refine_focal_length = False
    po.mapper.abs_pose_refine_extra_params = False
    po.mapper.init_min_num_inliers = options.init_min_num_inliers
    po.num_threads = options.num_threads
    po.random_seed = options.seed
    po.mapper.random_seed = options.seed
    po.triangulation.random_seed = options.seed
    return po


def _match(pycolmap: Any, database: Path, matching: str, options: RecoveryOptions, device: Any) -> None:
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = options.num_threads
    if matching == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=mo, device=device)
        return
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = options.sequential_overlap
    pairing.num_threads = options.num_threads
    if options.vocab_tree_path is not None:
        pairing.loop_detection = True
        pairing.vocab_tree_path = str(options.vocab_tree_path)
    pycolmap.match_sequential(database, matching_options=mo, pairing_options=pairing, device=device)


def _observations(image: Any, xyz: dict[int, np.ndarray]) -> Observations:
    """Observed sparse points of one registered image with their depth in that camera."""
    pts = image.get_observation_points2D()
    if not pts:
        return Observations(np.zeros((0, 2)), np.zeros(0), np.zeros(0, dtype=np.int64))
    xy = np.array([p.xy for p in pts], dtype=np.float64)
    ids = np.array([p.point3D_id for p in pts], dtype=np.int64)
    world = np.stack([xyz[int(i)] for i in ids])
    w2c = image.cam_from_world().matrix()  # 3x4
    depth = world @ w2c[:3, :3].T[:, 2] + w2c[2, 3]
    return Observations(xy, depth, ids)


def import_pycolmap() -> Any:
    """The ``pycolmap`` module; ``NotAvailable`` with the install command when it cannot be imported."""
    try:
        import pycolmap
    except ImportError as e:
        raise NotAvailable(f"pose recovery needs pycolmap (a dependency of this package): pip install "
                           f"'pycolmap>=4.0' ({e})") from None
    return pycolmap


def recover_poses(image_paths: Sequence[Path], camera: PinholeCamera, work_dir: Path,
                  options: RecoveryOptions | None = None) -> Recovery:
    """Recover the poses of ``image_paths`` (capture order) seen by one fixed pinhole ``camera``.

    ``work_dir`` receives COLMAP's database, the staged image links and the sparse models (``sparse/<i>``).
    Images whose size differs from the camera's raise ValueError naming the file (the intrinsics would be
    wrong). A sequence that COLMAP cannot reconstruct returns a Recovery with nothing registered.
    """
    pycolmap = import_pycolmap()
    options = options or RecoveryOptions()
    image_paths = [Path(p) for p in image_paths]
    for p in image_paths:
        size = image_size(p)
        if size != (camera.width, camera.height):
            raise ValueError(f"{p}: image size {size[0]}x{size[1]} differs from the camera's "
                             f"{camera.width}x{camera.height}")
    matching = options.matching_for(len(image_paths))
    empty = Recovery(len(image_paths), [], np.zeros((0, 4, 4)), [], float("nan"), 0, 0, matching)
    if len(image_paths) < 2:
        return empty
    pycolmap.logging.minloglevel = 0 if options.verbose else 2
    pycolmap.set_random_seed(options.seed)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    database.unlink(missing_ok=True)  # left by an interrupted run: start afresh
    shutil.rmtree(work_dir / "sparse", ignore_errors=True)
    stage = work_dir / "images"
    names = _stage_images(image_paths, stage)
    device = pycolmap.Device.auto  # CUDA SIFT and matching when this pycolmap build has it

    reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE", camera_params=_camera_params(camera))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = options.max_num_features
    extraction.num_threads = options.num_threads
    seconds = {}
    start = time.perf_counter()
    pycolmap.extract_features(database, stage, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=device)
    seconds["extract"] = round(time.perf_counter() - start, 3)
    _match(pycolmap, database, matching, options, device)
    seconds["match"] = round(time.perf_counter() - start - seconds["extract"], 3)
    models = pycolmap.incremental_mapping(database, stage, work_dir / "sparse",
                                          options=_mapping_options(pycolmap, options))
    seconds["map"] = round(time.perf_counter() - start - seconds["extract"] - seconds["match"], 3)
    if not models:
        return replace(empty, seconds=seconds)
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    index_of = {name: i for i, name in enumerate(names)}
    xyz = {int(pid): np.asarray(p.xyz, dtype=np.float64) for pid, p in rec.points3D.items()}
    regs = sorted((index_of[rec.images[i].name], rec.images[i]) for i in rec.reg_image_ids())
    c2w = np.zeros((len(regs), 4, 4))
    obs = []
    for k, (_, image) in enumerate(regs):
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        c2w[k] = np.linalg.inv(w2c)
        obs.append(_observations(image, xyz))
    cam = rec.cameras[next(iter(rec.cameras))]
    return Recovery(len(image_paths), [i for i, _ in regs], c2w, obs, float(rec.compute_mean_reprojection_error()),
                    int(rec.num_points3D()), len(models), matching, [float(v) for v in cam.params], seconds)


def recovery_json(recovery: Recovery, names: Sequence[str]) -> dict[str, Any]:
    """The ``recover`` output: ``{"frames": [{"image": name, "c2w": 4x4}], "registered": n,
    "mean_reprojection_error": e}`` (c2w OpenCV, reconstruction units; ``names`` indexed like the input)."""
    frames = [{"image": names[i], "c2w": c.tolist()} for i, c in zip(recovery.indices, recovery.c2w)]
    err = recovery.mean_reprojection_error
    return {"frames": frames, "registered": recovery.registered,
            "mean_reprojection_error": None if not np.isfinite(err) else err}
