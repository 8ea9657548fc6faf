"""A user's stereo input made model-ready: the images, their calibration, and the pair transform.

``sgmodel predict`` reads a pair (``--left/--right``) or a stereo video (``sgmodel.video``) into raw
``Pair`` s, then turns each into a model-ready one with one function, ``PairTransform`` (``prepare_pairs``):
a raw rig's pair is rectified first (``--rig``, ``rectify_pair``: ``sgmodel.rectify``), then resized to the
model's size with K (and doffs) scaled (``resize_pair``); still pairs and video frames take the same steps.

Images are [B,3,H,W] float32 in [0,1]; K in pixels of those images (OpenCV axes, pixel centres at +0.5).
Errors in the inputs raise ``PredictError`` (or ``CalibError``), naming the file or flag.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from scenesplat_stereo.encode import decode_image

from . import rig
from .calib import Calibration, calib_from_flags, read_calib
from .rectify import Rectification

#: Model input sides are multiples of this (the decoder's coarsest feature stride).
SIZE_MULTIPLE = 16
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


#: Raw pair -> model-ready pair (``prepare_pairs``).
PairTransform = Callable[[Pair], Pair]


def to_tensor(rgb: np.ndarray) -> torch.Tensor:
    """uint8 (or float in [0,1]) RGB [H,W,3] or [B,H,W,3] -> [B,3,H,W] float32 in [0,1]."""
    img = torch.from_numpy(np.ascontiguousarray(rgb))
    img = (img if img.ndim == 4 else img[None]).permute(0, 3, 1, 2)
    return img.float() / 255.0 if rgb.dtype == np.uint8 else img.float().clamp(0, 1)


def read_image(path: str, flag: str) -> torch.Tensor:
    """Decode an image file with OpenImageIO -> [1,3,H,W] float32 in [0,1] (grey repeated, alpha dropped)."""
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
    return to_tensor(arr[:, :, :1].repeat(3, 2) if arr.shape[2] < 3 else arr[:, :, :3])


def read_calibration(args: argparse.Namespace, width: int, height: int, image: str
                     ) -> tuple[Calibration, Rectification | None]:
    """The calibration flags (``--calib FILE``, ``--intrinsics`` with ``--baseline``, or a raw rig's ``--rig``),
    checked against the images' size (``image`` names them in errors): the calibration of the model's pair,
    and the rectification that makes it from the raw images (None for a rectified input)."""
    if args.calib and (args.intrinsics or args.baseline):
        raise PredictError("give either --calib or --intrinsics with --baseline, not both")
    if args.rig and (args.calib or args.intrinsics or args.baseline):
        raise PredictError("--rig rectifies a raw pair with its own calibration: give no --calib, --intrinsics or "
                           "--baseline with it")
    if args.rig:
        stereo_rig = rig.read_rig(args.rig, args.rig_units)
        stereo_rig.check_size(width, height, image)
        rectification = Rectification.of(stereo_rig, (width, height))
        return rectification.calibration, rectification
    if args.calib:
        calib = read_calib(args.calib)
    elif args.intrinsics and args.baseline is not None:
        calib = calib_from_flags(args.intrinsics, args.baseline)
    else:
        raise PredictError("missing calibration: give --calib FILE, --intrinsics fx,fy,cx,cy and --baseline B, or the "
                           "raw rig's --rig FILE")
    calib.check_size(width, height, image)
    return calib, None


def read_pair(args: argparse.Namespace) -> Pair:
    """Validate and read ``--left``, ``--right`` and the calibration (all checks that need no model)."""
    left, right = read_image(args.left, "--left"), read_image(args.right, "--right")
    if left.shape != right.shape:
        raise PredictError(f"--left {args.left} is {left.shape[3]}x{left.shape[2]} but --right {args.right} "
                           f"is {right.shape[3]}x{right.shape[2]}: a rectified pair has one size")
    return Pair(left, right, *read_calibration(args, left.shape[3], left.shape[2], f"--left {args.left}"))


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


def rectify_pair(pair: Pair) -> Pair:
    """A raw rig's pair rectified (``Rectification.rectify_tensors``, on the CPU); other pairs as they are."""
    if pair.rectification is None or pair.rectified:
        return pair
    left, right = pair.rectification.rectify_tensors(pair.left.cpu(), pair.right.cpu())
    return Pair(left, right, pair.calib, pair.rectification, rectified=True)


def prepare_pairs(short_side: int) -> PairTransform:
    """The transform from a raw pair to the model's input: ``rectify_pair``, then ``resize_pair`` to
    ``short_side``."""
    return lambda pair: resize_pair(rectify_pair(pair), short_side)
