"""Is this pair rectified, and is the left image on the left? A check from matched features before the model.

A rectified pair puts every scene point on one image row in both images, to the right in the left image:
the vertical disparity dy = y_right - y_left is zero and the disparity d = x_left - x_right (+ doffs, the
principal-point offset of Middlebury pairs) is positive. ``measure`` matches SIFT features (OpenCV; the
images are first scaled so that the long side is at most ``MAX_SIDE``; Lowe's ratio test, then a RANSAC
fundamental matrix, then a robust cut of dy far from its median (``OUTLIER_SIGMAS``) remove mismatches) and
reports, in pixels of the input images:

* the median and the 95th percentile of |dy| (a rectified pair: under ``DY_MEDIAN_MAX`` = 1 px and
  ``DY_P95_MAX`` = 2 px; SIFT places features to a few tenths of a pixel);
* the fraction of matches with d < -``NEGATIVE_MARGIN`` (over ``NEGATIVE_MAX`` = half of them: the images
  are swapped; a distant scene has d near 0 on both sides and does not trigger it).

Fewer than ``MIN_MATCHES`` matches leave the pair unverified (also a warning). Warnings print as one line
with the numbers and the likely cause; ``--strict`` makes them an error (exit 2).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from scenesplat_stereo.shards.encode import to_uint8

log = logging.getLogger(__name__)

#: Thresholds on |dy| (pixels of the input images): median, 95th percentile.
DY_MEDIAN_MAX, DY_P95_MAX = 1.0, 2.0
#: A disparity below -NEGATIVE_MARGIN pixels counts as negative; more than NEGATIVE_MAX of them: swapped.
NEGATIVE_MARGIN, NEGATIVE_MAX = 0.5, 0.5
#: Fewer matches than this: the check cannot tell.
MIN_MATCHES = 30
#: The check runs on images scaled down to this long side (pixels) when they are larger.
MAX_SIDE = 1280
#: SIFT features per image, Lowe's ratio, RANSAC threshold (pixels of the scaled images).
MAX_FEATURES, RATIO, RANSAC_PX = 2000, 0.75, 1.5
#: Mismatches left by RANSAC (repeated texture): dy farther from the median than OUTLIER_SIGMAS robust
#: standard deviations (1.4826 MAD), and at least OUTLIER_SIGMAS * OUTLIER_FLOOR pixels, are dropped.
OUTLIER_SIGMAS, OUTLIER_FLOOR = 10.0, 0.5


class StereoCheckError(ValueError):
    """The pair failed the stereo check under ``--strict``."""


@dataclass(frozen=True)
class StereoCheck:
    """What the check measured (pixels of the input images) and its warnings (empty: the pair looks fine)."""

    matches: int
    dy_median: float
    dy_p95: float
    dy_shift: float
    negative_fraction: float
    disparity: tuple[float, float, float]
    warnings: tuple[str, ...]

    def summary(self) -> str:
        """One line for logs: the figures and the verdict."""
        if self.matches < MIN_MATCHES:
            figures = f"{self.matches} feature matches (too few to measure)"
        else:
            d5, d50, d95 = self.disparity
            figures = (f"{self.matches} matches, vertical disparity median {self.dy_median:.2f} px (95th percentile "
                       f"{self.dy_p95:.2f} px), {self.negative_fraction:.0%} negative disparity, disparity "
                       f"{d5:.1f} / {d50:.1f} / {d95:.1f} px (5/50/95%)")
        return f"stereo check: {figures}: {'WARNING' if self.warnings else 'ok'}"

    def to_json(self) -> dict:
        """The figures as JSON values (null where too few matches left nothing to measure)."""
        number = lambda x: None if np.isnan(x) else x  # noqa: E731
        return {"matches": self.matches, "dy_median_px": number(self.dy_median), "dy_p95_px": number(self.dy_p95),
                "dy_shift_px": number(self.dy_shift), "negative_fraction": number(self.negative_fraction),
                "disparity_p5_p50_p95_px": [number(x) for x in self.disparity], "warnings": list(self.warnings)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--strict``, shared by ``sgmodel predict`` and ``sgmodel rectify``."""
    parser.add_argument("--strict", action="store_true",
                        help="stop with exit status 2 when the stereo check warns (vertical disparity over "
                             f"{DY_MEDIAN_MAX:g} px median / {DY_P95_MAX:g} px 95th percentile, mostly negative "
                             f"disparity, or fewer than {MIN_MATCHES} matches)")


def _grey(image) -> np.ndarray:
    """[1,3,H,W] tensor or [H,W,3] / [H,W] array (uint8 or float in [0, 1]) -> uint8 [H,W]."""
    if isinstance(image, torch.Tensor):
        image = image[0].permute(1, 2, 0).numpy() if image.ndim == 4 else image.numpy()
    image = to_uint8(np.asarray(image))
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 and image.shape[2] == 3 else image.squeeze()


def matches(left, right, max_side: int = MAX_SIDE) -> tuple[np.ndarray, np.ndarray]:
    """Matched SIFT feature positions [n,2] (x, y; pixels of the input images, OpenCV's integer centres) in
    the left and the right image, after the ratio test and a RANSAC fundamental matrix; SIFT runs on the
    images scaled to a long side of at most ``max_side`` pixels."""
    grey = [_grey(left), _grey(right)]
    h, w = grey[0].shape
    scale = min(1.0, max_side / max(h, w))
    if scale < 1:
        grey = [cv2.resize(g, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA) for g in grey]
    sift = cv2.SIFT_create(nfeatures=MAX_FEATURES)
    (k1, d1), (k2, d2) = (sift.detectAndCompute(g, None) for g in grey)
    if d1 is None or d2 is None or len(k1) < 2 or len(k2) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    p1 = np.array([k1[m.queryIdx].pt for m in good], dtype=np.float64).reshape(-1, 2)
    p2 = np.array([k2[m.trainIdx].pt for m in good], dtype=np.float64).reshape(-1, 2)
    if len(good) >= 8:
        _, inliers = cv2.findFundamentalMat(p1, p2, cv2.FM_RANSAC, RANSAC_PX, 0.999)
        if inliers is not None:
            p1, p2 = p1[inliers.ravel() > 0], p2[inliers.ravel() > 0]
    # SIFT positions have integer pixel centres at every scale: x_in = (x_scaled + 0.5) / scale - 0.5.
    return (p1 + 0.5) / scale - 0.5, (p2 + 0.5) / scale - 0.5


def measure(left, right, doffs: float = 0.0, rectified_here: bool = False, max_side: int = MAX_SIDE) -> StereoCheck:
    """The check of a pair (tensors [1,3,H,W] or arrays [H,W,3], uint8 or float in [0, 1]). ``doffs``: the
    pair's principal-point disparity offset (pixels, Middlebury); ``rectified_here``: the pair was rectified
    from ``--rig`` (the likely cause of a vertical disparity is then the calibration, not missing
    rectification); ``max_side``: see ``matches``."""
    p1, p2 = matches(left, right, max_side)
    if len(p1):
        dev = np.abs((p2[:, 1] - p1[:, 1]) - np.median(p2[:, 1] - p1[:, 1]))
        keep = dev <= OUTLIER_SIGMAS * max(1.4826 * np.median(dev), OUTLIER_FLOOR)
        p1, p2 = p1[keep], p2[keep]
    n = len(p1)
    if n < MIN_MATCHES:
        return StereoCheck(n, float("nan"), float("nan"), float("nan"), float("nan"), (float("nan"),) * 3,
                           (f"only {n} feature matches between the images ({MIN_MATCHES} needed): the check cannot "
                            f"tell whether the pair is rectified (textureless, very dark or unrelated images?)",))
    dy = p2[:, 1] - p1[:, 1]
    d = p1[:, 0] - p2[:, 0] + doffs
    ady = np.abs(dy)
    dy_median, dy_p95, shift = float(np.median(ady)), float(np.percentile(ady, 95)), float(np.median(dy))
    negative = float(np.mean(d < -NEGATIVE_MARGIN))
    disparity = tuple(float(x) for x in np.percentile(d, [5, 50, 95]))
    warnings = []
    if dy_median > DY_MEDIAN_MAX or dy_p95 > DY_P95_MAX:
        uniform = abs(shift) > DY_MEDIAN_MAX and np.median(np.abs(dy - shift)) < 0.5 * abs(shift)
        pattern = (f"nearly the same everywhere (the right image {shift:+.1f} px lower)" if uniform else
                   "varying across the image")
        if rectified_here:
            cause = ("the calibration does not fit these images (another rig, another resolution or zoom, a moved "
                     "lens, or cam0 and cam1 mixed up)")
        elif uniform:
            cause = ("the images were cropped or shifted differently, or the pair is not rectified (one camera "
                     "tilted): give the raw calibration with --rig to rectify it")
        else:
            cause = ("the pair is not rectified, or was rectified with another calibration: give the raw "
                     "calibration with --rig and let sgmodel rectify the pair")
        warnings.append(f"vertical disparity median {dy_median:.2f} px, 95th percentile {dy_p95:.2f} px over {n} "
                        f"matches, {pattern} (a rectified pair stays under {DY_MEDIAN_MAX:g} px and "
                        f"{DY_P95_MAX:g} px): {cause}")
    if negative > NEGATIVE_MAX and warnings:  # not rectified (or by a calibration that does not fit): say that
        cause = ("the calibration that rectified them does not fit these images (one of another resolution?)"
                 if rectified_here else "the pair is not rectified")
        warnings.append(f"{negative:.0%} of {n} matches have negative disparity (median {disparity[1]:+.1f} px): with "
                        f"the vertical disparity above, {cause} is the likelier cause than swapped images; fix that "
                        f"first")
    elif negative > NEGATIVE_MAX:
        warnings.append(f"{negative:.0%} of {n} matches have negative disparity (median {disparity[1]:+.1f} px): the "
                        f"left and right images are probably swapped (--left must be the left camera's image)")
    return StereoCheck(n, dy_median, dy_p95, shift, negative, disparity, tuple(warnings))


def stderr_line(line: str) -> None:
    """One warning through ``logging`` (a command prints it as ``<command>: warning: ...`` on stderr)."""
    log.warning(line.removeprefix("warning: "))


def run_check(left, right, strict: bool, doffs: float = 0.0, rectified_here: bool = False, log=print,
              warn=stderr_line) -> StereoCheck:
    """``measure`` with its summary line logged and its warnings given to ``warn`` as one line (stderr);
    StereoCheckError under ``strict`` when it warns."""
    check = measure(left, right, doffs, rectified_here)
    log(check.summary())
    if check.warnings:
        message = "stereo check: " + "; ".join(check.warnings)
        if strict:
            raise StereoCheckError(f"{message} (--strict)")
        warn(f"warning: {message}")
    return check
