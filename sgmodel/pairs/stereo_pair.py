"""One stereo pair's images: read from disk, the ``Pair`` record (images and calibration), the model's size.

``read_image`` decodes a user's image with OpenImageIO (any format it reads; grey repeated, alpha dropped,
turned upright by the EXIF Orientation tag) and refuses one smaller than ``MIN_IMAGE_SIDE`` pixels a side;
``resize_pair`` brings a pair to the model's size (``model_size``: the short side given, aspect kept, sides
multiples of ``SIZE_MULTIPLE``) with K and doffs scaled per axis. This module sits below ``sgmodel.pairs.prepare``
(calibration flags, a raw rig's rectification, the pair transform) and ``sgmodel.pairs.rectify``, and imports
neither. Images are [B,3,H,W] float32 in [0,1]; K in pixels of those images (pixel centres at +0.5).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from scenesplat_stereo.shards.encode import decode_image
from sgmodel.pairs.calib import Calibration

if TYPE_CHECKING:
    from sgmodel.pairs.rectify import Rectification

#: Model input sides are multiples of this (the decoder's coarsest feature stride).
SIZE_MULTIPLE = 16
#: Smallest image side accepted, pixels (stereo matching needs a few pixels of context; 1x1 is no pair).
MIN_IMAGE_SIDE = SIZE_MULTIPLE
_IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".ppm", ".pgm", ".pfm", ".webp"}


class PredictError(ValueError):
    """Bad input to ``sgmodel predict``; the message names the file or flag."""


@dataclass
class Pair:
    """Left and right images [B,3,H,W] float32 in [0,1] (B = 1 for a still pair) and the calibration of
    these H x W pixels (the same for every item). With ``rectification`` (``--rig``), ``calib`` is the
    rectified pair's: the images are raw until ``rectify_pair``, rectified after it."""

    left: torch.Tensor
    right: torch.Tensor
    calib: Calibration
    rectification: Rectification | None = None
    rectified: bool = False

    def model_inputs(self, device: torch.device | str) -> tuple[torch.Tensor, ...]:
        """(left, right, K [B,3,3], baseline [B] metres) on ``device``: what a model or baseline takes."""
        n = self.left.shape[0]
        K = torch.as_tensor(self.calib.K, dtype=torch.float32, device=device)[None].expand(n, 3, 3)
        baseline = torch.full((n,), self.calib.baseline, dtype=torch.float32, device=device)
        return self.left.to(device), self.right.to(device), K, baseline


def to_tensor(rgb: np.ndarray) -> torch.Tensor:
    """uint8 (or float in [0,1]) RGB [H,W,3] or [B,H,W,3] -> [B,3,H,W] float32 in [0,1]."""
    img = torch.from_numpy(np.ascontiguousarray(rgb))
    img = (img if img.ndim == 4 else img[None]).permute(0, 3, 1, 2)
    return img.float().div_(255.0) if rgb.dtype == np.uint8 else img.float().clamp(0, 1)  # (a new tensor: in place)


def read_image(path: str, flag: str) -> torch.Tensor:
    """Decode an image file with OpenImageIO -> [1,3,H,W] float32 in [0,1] (grey repeated, alpha dropped, turned
    upright by its EXIF Orientation tag as OpenCV's ``imread`` does: ``encode.decode_image``)."""
    p = Path(path)
    if not p.is_file():
        raise PredictError(f"{flag} {path}: file not found")
    if p.suffix.lower() not in _IMAGE_EXTS:
        raise PredictError(f"{flag} {path}: unsupported image type {p.suffix!r} ({', '.join(sorted(_IMAGE_EXTS))})")
    try:
        arr = decode_image(p.read_bytes(), p.suffix)
    except (ValueError, OSError) as e:
        raise PredictError(f"{flag} {path}: not a readable image ({e})") from None
    if arr.shape[2] not in (1, 2, 3, 4):
        raise PredictError(f"{flag} {path}: expected 1 to 4 channels, got {arr.shape[2]}")
    if min(arr.shape[:2]) < MIN_IMAGE_SIDE:
        raise PredictError(f"{flag} {path}: {arr.shape[1]}x{arr.shape[0]} pixels is too small for a stereo pair "
                           f"(both sides must be >= {MIN_IMAGE_SIDE})")
    return to_tensor(arr[:, :, :1].repeat(3, 2) if arr.shape[2] < 3 else arr[:, :, :3])


def model_size(width: int, height: int, short_side: int) -> tuple[int, int]:
    """(W', H'): short side scaled to ``short_side``, aspect kept, each side rounded to a multiple of 16."""
    s = short_side / min(width, height)
    return tuple(max(SIZE_MULTIPLE, SIZE_MULTIPLE * round(x * s / SIZE_MULTIPLE)) for x in (width, height))


def resize_pair(pair: Pair, short_side: int) -> Pair:
    """The pair resized to ``model_size`` (bilinear, antialiased) with K and doffs scaled per axis."""
    h, w = pair.left.shape[2:]
    w2, h2 = model_size(w, h, short_side)
    if (w2, h2) == (w, h):
        return pair
    resize = lambda x: F.interpolate(x, size=(h2, w2), mode="bilinear", antialias=True,  # noqa: E731
                                     align_corners=False).clamp(0, 1)
    return Pair(resize(pair.left), resize(pair.right), pair.calib.scaled(w2 / w, h2 / h), pair.rectification,
                pair.rectified)
