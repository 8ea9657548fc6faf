"""The sample record (SPEC section 5): a sample's key, its ``<key>.json`` (``SampleMeta``, the one reader and
writer of its fields) and how its images are stored (``JPEG_QUALITY``). Everything that writes or reads
shards (the build, the importers, the IRS pipeline, the model's loader) agrees on it here.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scenesplat_stereo.build.protocol import SamplePlan

JPEG_QUALITY = 92  # stored images (appendix B "Rendering and valid masks")


def sample_key(scene: str, frame: int) -> str:
    """WebDataset key of a sample (SPEC section 5)."""
    return f"{scene}__{frame:06d}"


class SampleMetaError(ValueError):
    """A sample JSON that does not hold a valid ``SampleMeta``; the message names the source and field."""


_KEY_RE = re.compile(r"^[^./\s]+$")  # WebDataset keys: no '.', '/' or whitespace (shards.check_key)
CAMERA_CONVENTION = "opencv"  # everything stored on disk is OpenCV c2w (SPEC section 1)


@dataclass(frozen=True, eq=False)
class SampleMeta:
    """The ``<key>.json`` member of a sample (SPEC section 5): the one reader and writer of its fields.

    ``key`` ("<scene>__<frame:06d>"), ``scene``, ``subset``, ``frame`` (index into the teacher's
    trajectory, or the IRS frame number), ``width``/``height`` (pixels), ``K`` [3,3] (pixels, finite,
    positive focal lengths), ``baseline`` (> 0) and ``rho`` (>= 0) in metres, ``teacher_psnr`` (dB or
    None), ``c2w_left`` [4,4] and ``c2w_right`` [4,4] or None (OpenCV c2w, metres), ``target_ids`` (the
    index j of each stored target; member names ``target_<jj>.jpg``/``mask_<jj>.png``), ``targets`` [T,4,4]
    (c2w of each target in ``target_ids`` order, T >= 1), ``camera_convention`` (always "opencv").
    IRS shards (pipelines/irs_targets.py) add ``target_frames`` (IRS frame number of each target) and
    ``target_coverage`` (frustum coverage of each target in [0, 1]); None elsewhere, and then not
    written. Arrays are float64 and read-only. Equality compares the JSON bytes.

    ``from_json`` checks types, shapes, finiteness and ranges only; whether the poses follow the
    protocol (rigid, right = T_L Trans(B,0,0), Fibonacci targets) is ``inspect``'s check.
    """

    key: str
    scene: str
    subset: str
    frame: int
    width: int
    height: int
    K: np.ndarray
    baseline: float
    rho: float
    teacher_psnr: float | None
    c2w_left: np.ndarray
    c2w_right: np.ndarray | None
    target_ids: tuple[int, ...]
    targets: np.ndarray
    camera_convention: str = CAMERA_CONVENTION
    target_frames: tuple[int, ...] | None = None
    target_coverage: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("K", "c2w_left", "c2w_right", "targets"):
            value = getattr(self, name)
            if value is not None:
                arr = np.array(value, dtype=np.float64)
                arr.flags.writeable = False
                object.__setattr__(self, name, arr)

    @property
    def num_targets(self) -> int:
        return len(self.target_ids)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SampleMeta) and self.to_json() == other.to_json()

    def __hash__(self) -> int:
        return hash(self.to_json())

    @classmethod
    def from_plan(cls, plan: SamplePlan) -> SampleMeta:
        """The record of a planned sample (``teacher_psnr`` None when unknown)."""
        psnr = plan.teacher_psnr
        return cls(key=plan.key, scene=plan.scene, subset=plan.subset, frame=int(plan.frame),
                   width=int(plan.width), height=int(plan.height), K=plan.K, baseline=float(plan.baseline),
                   rho=float(plan.rho), teacher_psnr=None if psnr is None else float(psnr),
                   c2w_left=plan.c2w_left, c2w_right=plan.c2w_right,
                   target_ids=tuple(int(j) for j in plan.target_ids), targets=plan.c2w_targets)

    def to_json(self) -> bytes:
        """Compact JSON bytes (no spaces), fields in the order of the class; None optionals left out."""
        doc: dict = {}
        for name in _FIELD_ORDER:
            value = getattr(self, name)
            if value is None and name in _OPTIONAL:
                continue
            if isinstance(value, np.ndarray):
                value = value.tolist()
            elif isinstance(value, tuple):
                value = list(value)
            doc[name] = value
        return json.dumps(doc, separators=(",", ":")).encode()

    @classmethod
    def from_json(cls, data: bytes | str, source: str) -> SampleMeta:
        """Parse and validate a sample JSON; ``source`` (e.g. "shard-000000.tar:<key>.json") starts every
        error message, which also names the field. Raises SampleMetaError."""
        try:
            doc = json.loads(data)
        except (ValueError, UnicodeDecodeError) as e:
            raise SampleMetaError(f"{source}: not valid JSON ({e})") from None
        if not isinstance(doc, dict):
            raise SampleMetaError(f"{source}: expected a JSON object, got {type(doc).__name__}")
        unknown = sorted(set(doc) - set(_FIELD_ORDER))
        if unknown:
            raise SampleMetaError(f"{source}: unknown fields {unknown}")
        missing = [f for f in _FIELD_ORDER if f not in doc and f not in _OPTIONAL]
        if missing:
            raise SampleMetaError(f"{source}: missing fields {missing}")
        f = _FieldReader(doc, source)
        targets = f.matrices("targets", (4, 4))
        count = len(targets)
        if count == 0:
            raise SampleMetaError(f"{source}: field 'targets': no targets stored (a sample needs at least one)")
        ids = f.ints("target_ids", count, low=0, high=99)  # two-digit member names target_<jj>
        if len(set(ids)) != len(ids):
            raise SampleMetaError(f"{source}: field 'target_ids': repeated ids {list(ids)}")
        key = f.text("key")
        if not _KEY_RE.match(key):
            raise SampleMetaError(f"{source}: field 'key': {key!r} must be non-empty, without '.', '/' or spaces")
        convention = f.text("camera_convention")
        if convention != CAMERA_CONVENTION:
            raise SampleMetaError(f"{source}: field 'camera_convention': {convention!r}, expected "
                                  f"{CAMERA_CONVENTION!r}")
        K = f.matrix("K", (3, 3))
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise SampleMetaError(f"{source}: field 'K': focal lengths must be positive, got "
                                  f"fx={K[0, 0]}, fy={K[1, 1]}")
        psnr = None if doc["teacher_psnr"] is None else f.number("teacher_psnr")
        return cls(key=key, scene=f.text("scene"), subset=f.text("subset"), frame=f.integer("frame", low=0),
                   width=f.integer("width", low=1), height=f.integer("height", low=1), K=K,
                   baseline=f.number("baseline", positive=True), rho=f.number("rho", low=0.0),
                   teacher_psnr=psnr, c2w_left=f.matrix("c2w_left", (4, 4)),
                   c2w_right=f.matrix("c2w_right", (4, 4)) if doc.get("c2w_right") is not None else None,
                   target_ids=ids, targets=targets, camera_convention=convention,
                   target_frames=f.ints("target_frames", count, low=0) if "target_frames" in doc else None,
                   target_coverage=(f.numbers("target_coverage", count, 0.0, 1.0)
                                    if "target_coverage" in doc else None))


_FIELD_ORDER = ("key", "scene", "subset", "frame", "width", "height", "K", "baseline", "rho", "teacher_psnr",
                "c2w_left", "c2w_right", "target_ids", "targets", "camera_convention", "target_frames",
                "target_coverage")
_OPTIONAL = frozenset({"c2w_right", "target_frames", "target_coverage"})


class _FieldReader:
    """Typed reads of one JSON object's fields; every failure is a SampleMetaError naming the field."""

    def __init__(self, doc: dict, source: str) -> None:
        self.doc, self.source = doc, source

    def fail(self, name: str, problem: str) -> SampleMetaError:
        return SampleMetaError(f"{self.source}: field {name!r}: {problem}")

    def text(self, name: str) -> str:
        value = self.doc[name]
        if not isinstance(value, str) or not value:
            raise self.fail(name, f"expected a non-empty string, got {value!r}")
        return value

    def integer(self, name: str, low: int) -> int:
        return self._int(name, self.doc[name], low)

    def _int(self, name: str, value, low: int, high: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
            bound = f">= {low}" if high is None else f"in {low}..{high}"
            raise self.fail(name, f"expected an integer {bound}, got {value!r}")
        return value

    def ints(self, name: str, count: int, low: int, high: int | None = None) -> tuple[int, ...]:
        values = self._list(name, count)
        return tuple(self._int(name, v, low, high) for v in values)

    def _list(self, name: str, count: int) -> list:
        values = self.doc[name]
        if not isinstance(values, list) or len(values) != count:
            got = f"{len(values)} entries" if isinstance(values, list) else repr(values)
            raise self.fail(name, f"expected a list of {count} (one per target), got {got}")
        return values

    def number(self, name: str, positive: bool = False, low: float | None = None) -> float:
        value = self.doc[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(name, f"expected a finite number, got {value!r}")
        if positive and not value > 0:
            raise self.fail(name, f"must be positive, got {value!r}")
        if low is not None and value < low:
            raise self.fail(name, f"must be >= {low}, got {value!r}")
        return float(value)

    def numbers(self, name: str, count: int, low: float, high: float) -> tuple[float, ...]:
        values = self._list(name, count)
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and low <= v <= high for v in values):
            raise self.fail(name, f"expected {count} numbers in [{low}, {high}], got {values!r}")
        return tuple(float(v) for v in values)

    def matrix(self, name: str, shape: tuple[int, int]) -> np.ndarray:
        return self._array(name, self.doc[name], shape)

    def matrices(self, name: str, shape: tuple[int, int]) -> np.ndarray:
        value = self.doc[name]
        if not isinstance(value, list):
            raise self.fail(name, f"expected a list of {shape[0]}x{shape[1]} matrices, got {value!r}")
        if not value:
            return np.zeros((0,) + shape)
        return self._array(name, value, (len(value),) + shape)

    def _array(self, name: str, value, shape: tuple[int, ...]) -> np.ndarray:
        try:
            arr = np.array(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(name, f"expected a numeric {'x'.join(map(str, shape))} array") from None
        if arr.shape != shape:
            raise self.fail(name, f"expected shape {shape}, got {arr.shape}")
        if not np.isfinite(arr).all():
            raise self.fail(name, "holds non-finite values")
        return arr
