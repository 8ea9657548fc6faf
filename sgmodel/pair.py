"""A user's stereo pair (``sgmodel predict``, ``sgmodel rectify``): its images from disk, with its calibration,
at the model's size.

``read_image(path, flag)`` -> [1,3,H,W] float32 in [0, 1]: any format OpenImageIO reads, grey repeated to RGB,
alpha dropped, 16-bit and float images scaled or clamped to [0, 1], turned upright by the EXIF Orientation
tag (``encode.decode_image``, as OpenCV's ``imread`` does; H and W are then those of the upright image).
``ImageError`` (a ValueError) names the flag and the file: missing, of an unknown type, unreadable, of an odd
channel count, or smaller than ``MIN_IMAGE_SIDE`` pixels a side (a 1x1 image is no stereo pair).

``Pair``: the two images and their ``Calibration`` (K of these pixels); ``resize_pair`` brings a pair to the
model's size (``model_size``: short side given, aspect kept, sides multiples of ``SIZE_MULTIPLE``), K and doffs
scaled per axis.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from scenesplat_stereo.encode import decode_image

from .calib import Calibration

if TYPE_CHECKING:
    from .rectify import Rectification

#: Model input sides are multiples of this (the decoder's coarsest feature stride).
SIZE_MULTIPLE = 16
#: Smallest image side accepted, pixels (stereo matching needs a few pixels of context).
MIN_IMAGE_SIDE = SIZE_MULTIPLE
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".ppm", ".pgm", ".pfm", ".webp"}


class ImageError(ValueError):
    """An input image that cannot be used; the message names the flag and the file."""


def read_image(path: str | Path, flag: str) -> torch.Tensor:
    """Decode an image file with OpenImageIO -> [1,3,H,W] float32 in [0,1] (see the module docstring)."""
    p = Path(path)
    if not p.is_file():
        raise ImageError(f"{flag} {path}: file not found")
    if p.suffix.lower() not in IMAGE_SUFFIXES:
        raise ImageError(f"{flag} {path}: unsupported image type {p.suffix!r} ({', '.join(sorted(IMAGE_SUFFIXES))})")
    try:
        arr = decode_image(p.read_bytes(), p.suffix)
    except (ValueError, OSError) as e:
        raise ImageError(f"{flag} {path}: not a readable image ({e})") from None
    if arr.shape[2] not in (1, 2, 3, 4):
        raise ImageError(f"{flag} {path}: expected 1 to 4 channels, got {arr.shape[2]}")
    if min(arr.shape[:2]) < MIN_IMAGE_SIDE:
        raise ImageError(f"{flag} {path}: {arr.shape[1]}x{arr.shape[0]} pixels is too small for a stereo pair "
                         f"(both sides must be >= {MIN_IMAGE_SIDE})")
    arr = arr[:, :, :1].repeat(3, 2) if arr.shape[2] < 3 else arr[:, :, :3]
    img = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)[None]
    return img.float() / 255.0 if arr.dtype == np.uint8 else img.float().clamp(0, 1)


@dataclass
class Pair:
    """The decoded pair [1,3,H,W] float32 in [0,1] and its calibration (of these H x W pixels); with
    ``--rig``, the pair as rectified and the rectification."""

    left: torch.Tensor
    right: torch.Tensor
    calib: Calibration
    rectification: Rectification | None = None


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
    return Pair(resize(pair.left), resize(pair.right), pair.calib.scaled(w2 / w, h2 / h), pair.rectification)
