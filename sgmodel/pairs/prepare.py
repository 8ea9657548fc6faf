"""A user's stereo input made model-ready: the images, their calibration, and the pair transform.

``sgmodel predict`` reads a pair (``--left/--right``) or a stereo video (``sgmodel.predict.video``) into raw
``Pair`` s, then turns each into a model-ready one with one function, ``PairTransform`` (``prepare_pairs``):
a raw rig's pair is rectified first (``--rig``, ``rectify_pair``: ``sgmodel.pairs.rectify``), then resized to the
model's size with K (and doffs) scaled (``resize_pair``); still pairs and video frames take the same steps.

Images are [B,3,H,W] float32 in [0,1]; K in pixels of those images (OpenCV axes, pixel centres at +0.5).
The ``Pair`` record, reading one image and resizing a pair live one level below, in ``sgmodel.pairs.stereo_pair``
(which ``sgmodel.pairs.rectify`` uses too). Errors in the inputs raise ``PredictError`` (or ``CalibError``), naming
the file or flag; a principal point outside the images is refused, one far from their centre warned about.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from sgmodel.pairs import rig
from sgmodel.pairs.calib import Calibration, calib_from_flags, read_calib
from sgmodel.pairs.rectify import Rectification
from sgmodel.pairs.stereo_pair import Pair, PredictError, read_image, resize_pair

#: Raw pair -> model-ready pair (``prepare_pairs``).
PairTransform = Callable[[Pair], Pair]


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
    calib.check_principal_point(width, height, image)
    return calib, None


def read_pair(args: argparse.Namespace) -> Pair:
    """Validate and read ``--left``, ``--right`` and the calibration (all checks that need no model)."""
    left, right = read_image(args.left, "--left"), read_image(args.right, "--right")
    if left.shape != right.shape:
        raise PredictError(f"--left {args.left} is {left.shape[3]}x{left.shape[2]} but --right {args.right} "
                           f"is {right.shape[3]}x{right.shape[2]}: a rectified pair has one size")
    return Pair(left, right, *read_calibration(args, left.shape[3], left.shape[2], f"--left {args.left}"))


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
