"""Rectification of a raw stereo rig's pair with OpenCV, and the way back to the raw left camera.

``Rectification.of(rig, size)`` runs ``cv2.stereoRectify`` (``cv2.fisheye.stereoRectify`` for equidistant
lenses) with ``CALIB_ZERO_DISPARITY`` and alpha / balance 0 (the rectified images hold only pixels both raw
images see: no black borders), and builds the ``initUndistortRectifyMap`` maps once (a video reuses them);
``rectify(left, right)`` remaps a pair (bilinear, edge pixels replicated). The rectified pair has one K, the
same size as the raw images, rows that are epipolar lines and the right camera at (baseline, 0, 0) in the
rectified left camera's frame.

Frames: the rectified left camera shares its centre with the raw left camera and is rotated from it by R1
(p_rect = R1 p_raw, OpenCV axes, metres). ``to_raw_frame`` takes Gaussians predicted in the rectified frame
back to the raw left camera's (rotation R1^T of means, orientations and SH colours: ``sgmodel.pairs.rotate``), so
the scene lines up with the user's raw images and poses. Depth maps stay images of the rectified left camera.

K conventions: OpenCV's matrices have pixel centres at integer coordinates; ``Rectification.K`` is in this
project's convention (centres at +0.5: cx, cy plus one half). ``sgmodel rectify`` writes the rectified pair
and its K.txt for other tools.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from scenesplat_stereo.common.files import atomic_write_bytes, atomic_write_json
from scenesplat_stereo.common.ownership import StagedFolder, check_apart, check_replaceable
from scenesplat_stereo.scene.cameras import baseline_doubt, rotation_angle_deg
from scenesplat_stereo.shards.encode import encode_png, to_uint8
from sgmodel.pairs import rig as rig_mod
from sgmodel.pairs import stereo_check
from sgmodel.pairs.calib import Calibration, foundation_stereo_text
from sgmodel.pairs.rig import FISHEYE, RigError, StereoRig
from sgmodel.pairs.rotate import rotate_gaussians
from sgmodel.pairs.stereo_pair import Pair, read_image, resize_pair

#: OpenCV's free scaling parameter (alpha for pinhole lenses, balance for fisheye): 0 = only valid pixels.
FREE_SCALING = 0.0
#: Rows of the right camera's projection allowed off zero (pixels) before a pair is not side by side.
_VERTICAL_TOLERANCE = 1e-6


@dataclass(frozen=True, eq=False)
class Rectification:
    """The rectification of ``rig`` for images of ``size`` = (width, height) pixels.

    K [3,3]: the rectified pair's intrinsics (pixels, centres at +0.5); baseline: metres; R1, R2 [3,3]:
    rotations from the raw left / right camera to the rectified one (p_rect = R p_raw); maps: the remap
    tables (x, y of the raw pixel, float32 [H,W]) of the left and the right image."""

    rig: StereoRig
    size: tuple[int, int]
    K: np.ndarray
    baseline: float
    R1: np.ndarray
    R2: np.ndarray
    maps: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

    @classmethod
    def of(cls, rig: StereoRig, size: tuple[int, int]) -> Rectification:
        """Run OpenCV's stereo rectification for images of ``size`` (RigError when it is not possible)."""
        rig.check_size(*size, "the images")
        T = rig.T.reshape(3, 1)
        if rig.model == FISHEYE:
            R1, R2, P1, P2, _ = cv2.fisheye.stereoRectify(
                rig.K1, rig.D1, rig.K2, rig.D2, size, rig.R, T, flags=cv2.CALIB_ZERO_DISPARITY, newImageSize=size,
                balance=FREE_SCALING, fov_scale=1.0)
        else:
            R1, R2, P1, P2 = cv2.stereoRectify(rig.K1, rig.D1, rig.K2, rig.D2, size, rig.R, T,
                                               flags=cv2.CALIB_ZERO_DISPARITY, alpha=FREE_SCALING)[:4]
        init = cv2.fisheye.initUndistortRectifyMap if rig.model == FISHEYE else cv2.initUndistortRectifyMap
        maps = [init(K, D, Ri, P, size, cv2.CV_32FC1) for K, D, Ri, P in ((rig.K1, rig.D1, R1, P1),
                                                                         (rig.K2, rig.D2, R2, P2))]
        K = P1[:, :3].astype(np.float64)
        if not np.isfinite(P2).all() or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise RigError(f"{rig.source}: OpenCV's stereo rectification failed (non-finite or non-positive "
                           f"focal length {K[0, 0]:g}); the cameras see too little of one another")
        if abs(P2[1, 3]) > _VERTICAL_TOLERANCE * abs(P2[0, 3]) or P2[0, 3] >= 0:
            raise RigError(f"{rig.source}: the rectified pair is not side by side with the right camera to the right "
                           f"(P2 = {P2.round(4).tolist()})")
        baseline = -float(P2[0, 3]) / float(P2[0, 0])
        K[:2, 2] += 0.5                                       # OpenCV's integer pixel centres -> +0.5
        return cls(rig, tuple(size), K, baseline, np.asarray(R1, np.float64), np.asarray(R2, np.float64),
                   tuple((m[0], m[1]) for m in maps))

    @property
    def calibration(self) -> Calibration:
        """The rectified pair's calibration (K, baseline, size) for ``sgmodel predict``."""
        return Calibration(self.K, self.baseline, 0.0, self.size, f"{self.rig.source} (rectified)")

    @property
    def rotation_deg(self) -> float:
        """Angle between the raw and the rectified left camera, degrees."""
        turned = np.eye(4)
        turned[:3, :3] = self.R1
        return float(rotation_angle_deg(np.eye(4), turned))

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw images [H,W] or [H,W,C] (uint8, uint16 or float32, H x W = ``size``) -> the rectified pair,
        same size and dtype (bilinear; pixels just outside the raw image replicate its edge)."""
        out = []
        for name, image, (mx, my) in (("left", left, self.maps[0]), ("right", right, self.maps[1])):
            if image.shape[:2] != (self.size[1], self.size[0]):
                raise RigError(f"{self.rig.source}: the {name} image is {image.shape[1]}x{image.shape[0]}, the "
                               f"rectification was made for {self.size[0]}x{self.size[1]}")
            out.append(cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        return out[0], out[1]

    def rectify_tensors(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The same for batches of float images [B,3,H,W] on the CPU (``sgmodel.predict.command``'s layout; a video's
        frames reuse the maps)."""
        pairs = [self.rectify(*(np.ascontiguousarray(x[b].permute(1, 2, 0).numpy(), dtype=np.float32)
                                for x in (left, right))) for b in range(left.shape[0])]
        return tuple(torch.from_numpy(np.stack([p[i] for p in pairs])).permute(0, 3, 1, 2).contiguous()
                     for i in (0, 1))

    def to_raw_frame(self, gaussians: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Gaussians predicted in the rectified left camera's frame -> the raw left camera's frame."""
        return rotate_gaussians(gaussians, self.R1.T)

    def summary(self) -> str:
        """One line: the rectified K and baseline, and how far the raw left camera turns."""
        K = self.K
        return (f"rectified with {self.rig.source} ({self.rig.model} lenses): K fx={K[0, 0]:.2f} fy={K[1, 1]:.2f} "
                f"cx={K[0, 2]:.2f} cy={K[1, 2]:.2f}, baseline {self.baseline:.4g} m, {self.size[0]}x{self.size[1]}; "
                f"the raw left camera is {self.rotation_deg:.2f} deg from the rectified one")

    def report(self, log=print, warn=stereo_check.stderr_line) -> None:
        """The summary to ``log``; an implausible baseline (``cameras.baseline_doubt``) to ``warn`` as a likely unit
        mistake (``--rig-units``)."""
        log(self.summary())
        doubt = baseline_doubt(self.baseline, f"--rig {self.rig.source}", "if the calibration's T is not in "
                               "metres, give --rig-units mm or cm", "if the calibration's T is in metres, leave "
                               "--rig-units out (it scales T from mm or cm)")
        if doubt:
            warn(f"warning: {doubt}")

    def to_json(self) -> dict:
        """What ``sgmodel rectify`` records beside the images (matrices as row lists)."""
        return {"rig": self.rig.source, "lens_model": self.rig.model, "size": list(self.size),
                "K": self.K.tolist(), "baseline_m": self.baseline, "R1": self.R1.tolist(), "R2": self.R2.tolist(),
                "conventions": "OpenCV axes; p_rect = R1 p_raw_left, p_rect_right = R2 p_raw_right; K with pixel "
                               "centres at +0.5; the right camera at (baseline, 0, 0) in the rectified left frame"}


@dataclass
class RigPrediction:
    """``predict_from_rig``'s result: gaussians (the Gaussians dict, batch 1) in the raw left camera's frame;
    depth z [1,1,h,w] metres, an image of the rectified left camera at the model's size, whose K and baseline
    are ``calibration``; the rectification; the stereo check; valid [1,N] bool, the Gaussians that stand on
    a stereo depth (``sgmodel.predict.export.to_scene(gaussians, 0, valid[0])`` keeps only those)."""

    gaussians: dict[str, torch.Tensor]
    depth: torch.Tensor
    calibration: Calibration
    rectification: Rectification
    check: stereo_check.StereoCheck
    valid: torch.Tensor


def _as_tensor(image, name: str) -> torch.Tensor:
    """[1,3,H,W] float tensor in [0,1], or an RGB array [H,W,3] (uint8, or float in [0, 1]) -> [1,3,H,W]."""
    if isinstance(image, torch.Tensor):
        if image.ndim != 4 or image.shape[:2] != (1, 3):
            raise ValueError(f"{name}: expected a [1, 3, H, W] tensor, got {tuple(image.shape)}")
        return image.detach().float().cpu()
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"{name}: expected an RGB image [H, W, 3], got shape {a.shape}")
    a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
    return torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1)[None]


def predict_from_rig(predictor, left, right, rig: StereoRig, short_side: int | None = None, strict: bool = False,
                     log=print) -> RigPrediction:
    """The Python API of ``sgmodel predict --rig``: a raw pair of ``rig``'s cameras -> a scene in the raw
    left camera's frame.

    predictor: ``sgmodel.model.network.load_predictor(checkpoint)``; left, right: RGB images [H,W,3] (uint8, or float
    in [0, 1]) or tensors [1,3,H,W] in [0, 1]; the pair is rectified, checked (``stereo_check``; StereoCheckError
    when it warns and ``strict``), resized to the model's size (short side ``short_side`` or the checkpoint's,
    sides multiples of 16) and predicted; the Gaussians are turned back into the raw left camera's frame.
    """
    left, right = _as_tensor(left, "left"), _as_tensor(right, "right")
    if left.shape != right.shape:
        raise RigError(f"left is {left.shape[3]}x{left.shape[2]} but right {right.shape[3]}x{right.shape[2]}: both "
                       f"cameras of a rig deliver one size")
    rect = Rectification.of(rig, (left.shape[3], left.shape[2]))
    rect.report(log)
    pair = Pair(*rect.rectify_tensors(left, right), rect.calibration, rect, rectified=True)
    check = stereo_check.run_check(pair.left, pair.right, strict, rectified_here=True, log=log)
    pair = resize_pair(pair, short_side or predictor.resolution)
    device = next(predictor.model.parameters()).device
    out = predictor.predict(*pair.model_inputs(device))
    return RigPrediction(rect.to_raw_frame(out.gaussians), out.depth, pair.calib, rect, check, out.valid)


# -------------------------------------------------------------------------------------- sgmodel rectify
RECTIFY_OWNER = "sgmodel rectify"  # recorded in OUT (ownership.OWNER_FILE): a later run may replace OUT


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``sgmodel rectify``."""
    parser.add_argument("--left", required=True, help="raw left image (the rig's first camera, cam0)")
    parser.add_argument("--right", required=True, help="raw right image (the rig's second camera, cam1)")
    rig_mod.add_arguments(parser, required=True)
    parser.add_argument("--out", required=True, help="output folder: left.png, right.png, K.txt, rectification.json")
    stereo_check.add_arguments(parser)


def rectify_command(args: argparse.Namespace, log=print) -> None:
    """Do the work of ``sgmodel rectify`` (raises a CalibError / ValueError naming the flag on bad input)."""
    check_apart(args.out, "--out", {"--left": args.left, "--right": args.right, "--rig": args.rig}, replaced=True)
    check_replaceable(args.out, "--out", RECTIFY_OWNER)
    rig = rig_mod.read_rig(args.rig, args.rig_units)
    left, right = read_image(args.left, "--left"), read_image(args.right, "--right")
    for flag, image in (("--left", left), ("--right", right)):
        rig.check_size(image.shape[3], image.shape[2], f"{flag} {getattr(args, flag[2:])}")
    if left.shape != right.shape:
        raise RigError(f"--left {args.left} is {left.shape[3]}x{left.shape[2]} but --right {args.right} is "
                       f"{right.shape[3]}x{right.shape[2]}: both cameras of a rig deliver one size")
    rect = Rectification.of(rig, (left.shape[3], left.shape[2]))
    left, right = rect.rectify_tensors(left, right)
    rect.report(log)
    check = stereo_check.run_check(left, right, args.strict, rectified_here=True, log=log)
    out = Path(args.out)
    with StagedFolder(out, RECTIFY_OWNER) as tmp:  # replaces OUT as a whole, or leaves it as it was
        for name, x in (("left", left), ("right", right)):
            atomic_write_bytes(tmp / f"{name}.png", encode_png(to_uint8(x[0].permute(1, 2, 0).numpy())))
        atomic_write_bytes(tmp / "K.txt", foundation_stereo_text(rect.K, rect.baseline).encode())
        atomic_write_json(tmp / "rectification.json", {**rect.to_json(), "check": check.to_json()}, indent=2)
    log(f"wrote {out}/: left.png, right.png, K.txt, rectification.json")


def run(args: argparse.Namespace) -> int:
    """Entry point of ``sgmodel rectify``: 0 on success (bad input raises a ValueError naming the flag or file;
    the command line makes it one line and exit 2)."""
    rectify_command(args)
    return 0
