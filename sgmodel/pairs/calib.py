"""Stereo calibration of a user's rectified pair: ``--calib FILE`` or ``--intrinsics fx,fy,cx,cy --baseline B``.

Two file formats are read (detected from the content):

* FoundationStereo demo (``K.txt``): line 1 holds the 9 numbers of the left K, row-major; line 2 the
  baseline in metres. No image size, doffs = 0.
* Middlebury 2014 ``calib.txt``: ``key=value`` lines, ``cam0=[fx 0 cx; 0 fy cy; 0 0 1]`` (left K),
  ``cam1=[...]`` (right K), ``doffs=`` (pixels, = cx1 - cx0), ``baseline=`` in millimetres, ``width=``,
  ``height=`` (pixels); ``ndisp``, ``isint``, ``vmin``, ``vmax``, ``dyavg``, ``dymax`` are read as numbers
  and not used.

``doffs`` is the difference of the two principal points in x: the disparity an encoder measures on the
images, d, is smaller than the geometric one by doffs, so depth is z = fx B / (d + doffs)
(``sgmodel.model.geometry.depth_from_disparity(..., doffs=)``). When the images are resized, doffs scales with the
width like cx (``Calibration.scaled``). Every problem raises ``CalibError`` naming the file (or flag), the
line and the field.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.cameras import baseline_doubt

_MIDDLEBURY_KEYS = ("cam0", "cam1", "doffs", "baseline", "width", "height", "ndisp", "isint", "vmin", "vmax",
                    "dyavg", "dymax")
_MIDDLEBURY_REQUIRED = ("cam0", "baseline")
#: Middlebury 2014 states the baseline in millimetres.
_MM = 1e-3
#: A principal point further than this fraction of the image size from its centre gets a warning.
OFF_CENTRE = 0.2
log = logging.getLogger(__name__)


class CalibError(ValueError):
    """Bad calibration input; the message names the file or flag, the line and the field."""


@dataclass(frozen=True)
class Calibration:
    """Left camera K [3,3] float64 (pixels), baseline (metres, > 0), doffs (pixels; 0 unless Middlebury),
    size (width, height) in pixels when the source states it, else None; source names the file or flags."""

    K: np.ndarray
    baseline: float
    doffs: float = 0.0
    size: tuple[int, int] | None = None
    source: str = ""

    def check_size(self, width: int, height: int, image: str) -> None:
        """Raise CalibError when the calibration states a size other than the image's (width x height)."""
        if self.size is not None and tuple(self.size) != (width, height):
            raise CalibError(f"{self.source}: width={self.size[0]}, height={self.size[1]} do not match "
                             f"{image} ({width}x{height})")

    def check_principal_point(self, width: int, height: int, image: str) -> None:
        """CalibError when the principal point (cx, cy) lies outside the image (width x height pixels); a
        warning when it lies more than ``OFF_CENTRE`` of the size from the centre, as a K computed for
        another resolution puts it (a K of twice the size lands near the far corner)."""
        cx, cy = self.K[0, 2], self.K[1, 2]
        if not (0 < cx < width and 0 < cy < height):
            raise CalibError(f"{self.source}: principal point cx={cx:g}, cy={cy:g} lies outside {image} "
                             f"({width}x{height} pixels): is the calibration for another image size?")
        off = max(abs(cx - width / 2) / width, abs(cy - height / 2) / height)
        if off > OFF_CENTRE:
            log.warning(f"{self.source}: principal point cx={cx:g}, cy={cy:g} is {100 * off:.0f}% of the image "
                        f"size from the centre of {image} ({width / 2:g}, {height / 2:g}): is the calibration for "
                        f"another image size?")

    def scaled(self, sx: float, sy: float) -> Calibration:
        """The calibration of the images resized by (sx, sy): fx, cx, doffs times sx; fy, cy times sy
        (pixel edges scale, so centres at +0.5 stay consistent); size None (the caller knows it)."""
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return dataclasses.replace(self, K=K, doffs=self.doffs * sx, size=None)


def _float(text: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise CalibError(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise CalibError(f"{where}: {text!r} is not a finite number")
    return value


def _check_K(K: np.ndarray, where: str) -> np.ndarray:
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise CalibError(f"{where}: focal lengths must be positive, got fx={fx:g}, fy={fy:g}")
    if K[0, 1] != 0 or K[1, 0] != 0 or tuple(K[2]) != (0.0, 0.0, 1.0):
        raise CalibError(f"{where}: K must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew), got {K.tolist()}")
    return K


def _check_baseline(b: float, where: str, scale: float = 1.0, hint: str = "") -> float:
    """The baseline ``b`` (in the file's unit) times ``scale`` (to metres): CalibError when not positive; a warning
    when implausible for a rig (``cameras.baseline_doubt``), with ``hint``: how the unit is read."""
    if b <= 0:
        raise CalibError(f"{where}: baseline must be positive, got {b:g}")
    doubt = baseline_doubt(b * scale, where, hint, hint)
    if doubt:
        log.warning(doubt)
    return b * scale


def _matrix(text: str, where: str) -> np.ndarray:
    """Middlebury ``[a b c; d e f; g h i]`` -> [3,3] float64."""
    m = re.fullmatch(r"\s*\[(.*)\]\s*", text)
    rows = m.group(1).split(";") if m else []
    if len(rows) != 3 or any(len(r.split()) != 3 for r in rows):
        raise CalibError(f"{where}: expected a 3x3 matrix [fx 0 cx; 0 fy cy; 0 0 1], got {text.strip()!r}")
    return np.array([[_float(v, where) for v in r.split()] for r in rows], dtype=np.float64)


def _read_middlebury(path: Path, lines: list[str]) -> Calibration:
    fields: dict[str, tuple[str, str]] = {}
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        key, sep, value = line.partition("=")
        key = key.strip()
        where = f"{path}: line {i} ({key})"
        if not sep or key not in _MIDDLEBURY_KEYS:
            raise CalibError(f"{path}: line {i}: expected one of {', '.join(_MIDDLEBURY_KEYS)} as key=value, "
                             f"got {line.strip()!r}")
        if key in fields:
            raise CalibError(f"{where}: {key} given twice")
        fields[key] = (value, where)
    for key in _MIDDLEBURY_REQUIRED:
        if key not in fields:
            raise CalibError(f"{path}: Middlebury calib.txt without {key}=")
    K = _check_K(_matrix(*fields["cam0"]), fields["cam0"][1])
    nums = {k: _float(*fields[k]) for k in fields if k not in ("cam0", "cam1")}
    if "cam1" in fields:
        K1 = _check_K(_matrix(*fields["cam1"]), fields["cam1"][1])
        if not np.allclose(K1[[0, 1, 1], [0, 1, 2]], K[[0, 1, 1], [0, 1, 2]], rtol=1e-6):
            raise CalibError(f"{fields['cam1'][1]}: a rectified pair has the same fx, fy and cy in cam0 and "
                             f"cam1, got {K.tolist()} and {K1.tolist()}")
    doffs = nums.get("doffs", float(K1[0, 2] - K[0, 2]) if "cam1" in fields else 0.0)
    baseline = _check_baseline(nums["baseline"], fields["baseline"][1], _MM,
                               "Middlebury 2014's baseline= is in millimetres (e.g. baseline=193.001)")
    size = None
    if "width" in fields or "height" in fields:
        if not ("width" in fields and "height" in fields):
            raise CalibError(f"{path}: width= and height= must be given together")
        for key in ("width", "height"):
            if nums[key] < 1 or nums[key] != int(nums[key]):
                raise CalibError(f"{fields[key][1]}: {key} must be a positive integer, got {nums[key]:g}")
        size = (int(nums["width"]), int(nums["height"]))
    return Calibration(K, baseline, doffs, size, str(path))


def _read_foundation_stereo(path: Path, lines: list[str]) -> Calibration:
    lines = [line for line in lines if line.strip()]
    if len(lines) != 2:
        raise CalibError(f"{path}: FoundationStereo format has 2 lines (9 numbers of K row-major; baseline in "
                         f"metres), got {len(lines)} non-empty lines")
    values = lines[0].split()
    if len(values) != 9:
        raise CalibError(f"{path}: line 1 (K) must hold 9 numbers, got {len(values)}")
    K = np.array([_float(v, f"{path}: line 1 (K)") for v in values], dtype=np.float64).reshape(3, 3)
    _check_K(K, f"{path}: line 1 (K)")
    b = lines[1].split()
    if len(b) != 1:
        raise CalibError(f"{path}: line 2 (baseline) must hold 1 number, got {len(b)}")
    baseline = _check_baseline(_float(b[0], f"{path}: line 2 (baseline)"), f"{path}: line 2 (baseline)",
                               hint="FoundationStereo's line 2 is in metres (120 mm is 0.12)")
    return Calibration(K, baseline, 0.0, None, str(path))


def foundation_stereo_text(K: np.ndarray, baseline: float) -> str:
    """The FoundationStereo ``K.txt`` of K [3,3] (pixels) and a baseline (metres), as ``read_calib`` reads it:
    the 9 numbers of K row-major on line 1, the baseline on line 2 (full float64 precision)."""
    return " ".join(repr(float(v)) for v in np.asarray(K, dtype=np.float64).ravel()) + f"\n{float(baseline)!r}\n"


def read_calib(path: str | Path) -> Calibration:
    """Read a FoundationStereo ``K.txt`` or a Middlebury 2014 ``calib.txt`` (detected from the content)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibError(f"{path}: calibration file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CalibError(f"{path}: cannot read the calibration file: {e}") from None
    lines = text.splitlines()
    if any(re.match(r"\s*cam0\s*=", line) for line in lines):
        return _read_middlebury(path, lines)
    first = next((line for line in lines if line.strip()), "")
    if "=" in text or not re.fullmatch(r"[\s0-9eE.+-]+", first):
        raise CalibError(f"{path}: unknown calibration format (expected the FoundationStereo K.txt: 9 numbers, "
                         f"then the baseline in metres; or a Middlebury 2014 calib.txt with cam0=[...])")
    return _read_foundation_stereo(path, lines)


def calib_from_flags(intrinsics: str, baseline: str | float) -> Calibration:
    """``--intrinsics fx,fy,cx,cy`` (pixels) and ``--baseline B`` (metres) -> Calibration."""
    values = [v for v in str(intrinsics).split(",")]
    if len(values) != 4:
        raise CalibError(f"--intrinsics: expected 4 comma-separated numbers fx,fy,cx,cy, got {intrinsics!r}")
    fx, fy, cx, cy = (_float(v.strip(), "--intrinsics") for v in values)
    K = _check_K(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64), "--intrinsics")
    b = _check_baseline(_float(str(baseline).strip(), "--baseline"), "--baseline",
                        hint="--baseline is in metres (120 mm is --baseline 0.12)")
    return Calibration(K, b, 0.0, None, "--intrinsics/--baseline")
