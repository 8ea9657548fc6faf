"""``sgmodel predict``: from a user's rectified stereo pair to a 3DGS scene in the left camera's frame.

Writes ``OUT/scene.ply`` (INRIA layout, SH degree 2, left camera frame, OpenCV axes, metres),
``OUT/depth.png`` (turbo colour map of the z-depth, red near, blue far), ``OUT/views/*.png`` (novel views
around the left camera) and ``OUT/orbit.gif``. ``--method forward-splat`` writes no ``scene.ply`` (it has
no Gaussians): its views are the z-buffered warp of the left image.

The pair is resized so its short side is the model's resolution (the checkpoint's, or ``--resolution``,
or 256 for the baselines), keeping the aspect ratio, each side rounded to a multiple of 16; K (and doffs)
are scaled by the same factors per axis, and the outputs are at that size. Every input is checked before
anything is written; outputs go to a temporary folder beside OUT and are moved into OUT at the end.
Errors in the inputs raise ``PredictError`` (or ``CalibError``); ``run`` turns them into exit status 2.

With ``--rig`` the pair is raw: it is rectified first (``sgmodel.rectify``), ``scene.ply`` is then in the raw
left camera's frame, while ``depth.png`` and the views stay images of the rectified left camera (the model's
input). Before the model runs, ``sgmodel.stereo_check`` measures the pair's vertical disparity and the sign
of its disparity and warns (``--strict``: exit 2); the summary repeats its figures.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from scenesplat_stereo.encode import decode_image, encode_png, to_uint8

from . import baselines, export, rig, stereo_check
from .bench import synced_clock
from .calib import CalibError, Calibration, calib_from_flags, read_calib
from .encoders import DEFAULT_ENCODER, EncoderFlagError
from .encoders.flags import add_encoder_arguments, build_encoder, merge_encoder
from .geometry import Z_MAX, depth_from_disparity
from .rectify import Rectification
from .render import render_views

#: Short side the baselines run at when neither a checkpoint nor --resolution says (SPEC section 7, S).
DEFAULT_RESOLUTION = 256
#: Model input sides are multiples of this (the decoder's coarsest feature stride).
SIZE_MULTIPLE = 16
#: Novel views sit this fraction of the median matched depth (z < z_max) away from the left camera.
VIEW_RADIUS = 0.15
#: Frames in the orbit animation.
ORBIT_FRAMES = 24
_IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".ppm", ".pgm", ".pfm", ".webp"}


class PredictError(ValueError):
    """Bad input to ``sgmodel predict``; the message names the file or flag."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``sgmodel predict``."""
    parser.add_argument("--left", required=True, help="left (reference) image of a rectified pair (raw with --rig)")
    parser.add_argument("--right", required=True, help="right image, same size as the left")
    parser.add_argument("--calib", help="FoundationStereo K.txt (K row-major; baseline in metres) or "
                        "Middlebury 2014 calib.txt")
    parser.add_argument("--intrinsics", help="fx,fy,cx,cy in pixels of the input images (instead of --calib)")
    parser.add_argument("--baseline", help="baseline in metres (with --intrinsics)")
    rig.add_arguments(parser)
    stereo_check.add_arguments(parser)
    parser.add_argument("--checkpoint", help="trained model checkpoint")
    parser.add_argument("--method", choices=baselines.METHODS,
                        help="a baseline without learned prediction instead of --checkpoint")
    parser.add_argument("--out", required=True, help="output folder (created; existing files replaced)")
    add_encoder_arguments(parser, f"the checkpoint's; {DEFAULT_ENCODER} for --method")
    parser.add_argument("--resolution", type=int, help="short side the model runs at (default: the "
                        f"checkpoint's; {DEFAULT_RESOLUTION} for --method)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")


@dataclass
class Pair:
    """The decoded pair [1,3,H,W] float32 in [0,1] and its calibration (of these H x W pixels); with
    ``--rig``, the pair as rectified and the rectification."""

    left: torch.Tensor
    right: torch.Tensor
    calib: Calibration
    rectification: Rectification | None = None


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
    arr = arr[:, :, :1].repeat(3, 2) if arr.shape[2] < 3 else arr[:, :, :3]
    img = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)[None]
    return img.float() / 255.0 if arr.dtype == np.uint8 else img.float().clamp(0, 1)


def read_pair(args: argparse.Namespace) -> Pair:
    """Validate and read the images and the calibration (all checks that need no model)."""
    left, right = read_image(args.left, "--left"), read_image(args.right, "--right")
    if left.shape != right.shape:
        raise PredictError(f"--left {args.left} is {left.shape[3]}x{left.shape[2]} but --right {args.right} "
                           f"is {right.shape[3]}x{right.shape[2]}: a rectified pair has one size")
    if args.calib and (args.intrinsics or args.baseline):
        raise PredictError("give either --calib or --intrinsics with --baseline, not both")
    if args.rig and (args.calib or args.intrinsics or args.baseline):
        raise PredictError("--rig rectifies a raw pair with its own calibration: give no --calib, --intrinsics or "
                           "--baseline with it")
    if args.rig:
        stereo_rig = rig.read_rig(args.rig, args.rig_units)
        stereo_rig.check_size(left.shape[3], left.shape[2], f"--left {args.left}")
        rectification = Rectification.of(stereo_rig, (left.shape[3], left.shape[2]))
        return Pair(*rectification.rectify_tensors(left, right), rectification.calibration, rectification)
    if args.calib:
        calib = read_calib(args.calib)
    elif args.intrinsics and args.baseline is not None:
        calib = calib_from_flags(args.intrinsics, args.baseline)
    else:
        raise PredictError("missing calibration: give --calib FILE, --intrinsics fx,fy,cx,cy and --baseline B, or the "
                           "raw rig's --rig FILE")
    calib.check_size(left.shape[3], left.shape[2], args.left)
    return Pair(left, right, calib)


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


def make_encoder(name: str | None, weights: str | None, repo: str | None, device: str):
    """The frozen stereo encoder of the baselines (``sgmodel.encoders``; its default when name is None)."""
    return build_encoder(merge_encoder(None, name, weights, repo), device)


class _Timer:
    """Wall time per stage (CUDA synchronised), printed as a table."""

    def __init__(self, device: torch.device) -> None:
        self.now = synced_clock(device)
        self.rows, self.t = [], self.now()

    def lap(self, stage: str) -> None:
        now = self.now()
        self.rows.append((stage, now - self.t))
        self.t = now

    def table(self) -> str:
        lines = ["| stage | seconds |", "|---|---:|"] + [f"| {s} | {t:.3f} |" for s, t in self.rows]
        return "\n".join(lines + [f"| total | {sum(t for _, t in self.rows):.3f} |"])


def _check_args(args: argparse.Namespace) -> None:
    if bool(args.checkpoint) == bool(args.method):
        raise PredictError("give exactly one of --checkpoint CKPT or --method {naive-gs,forward-splat}")
    if args.checkpoint and not Path(args.checkpoint).is_file():
        raise PredictError(f"--checkpoint {args.checkpoint}: file not found")
    if args.resolution is not None and args.resolution < SIZE_MULTIPLE:
        raise PredictError(f"--resolution must be at least {SIZE_MULTIPLE}, got {args.resolution}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise PredictError(f"--out {args.out}: exists and is not a folder")
    if not out.resolve().parent.is_dir():
        raise PredictError(f"--out {args.out}: parent folder {out.resolve().parent} does not exist")
    try:
        torch.device(args.device)
    except RuntimeError as e:
        raise PredictError(f"--device {args.device!r}: {e}") from None


def predict(args: argparse.Namespace, log=print) -> None:
    """Do the work of ``sgmodel predict`` (raises PredictError / CalibError on bad input)."""
    _check_args(args)
    device = torch.device(args.device)
    timer = _Timer(device)
    pair = read_pair(args)
    if pair.rectification is not None:
        timer.lap("read and rectify")
        pair.rectification.report(log)
    if args.checkpoint:
        from .model import load_predictor

        predictor = load_predictor(args.checkpoint, device, args.encoder_weights, args.encoder_repo, args.encoder)
        short = args.resolution or predictor.resolution
    else:
        encoder = make_encoder(args.encoder, args.encoder_weights, args.encoder_repo, device)
        short = args.resolution or DEFAULT_RESOLUTION
    timer.lap("load")
    check = stereo_check.run_check(pair.left, pair.right, args.strict, pair.calib.doffs, pair.rectification is not None,
                                   log)
    timer.lap("stereo check")
    pair = resize_pair(pair, short)
    _, _, h, w = pair.left.shape
    log(f"model size {w}x{h} (short side {short}, sides multiples of {SIZE_MULTIPLE}); K scaled to "
        f"fx={pair.calib.K[0, 0]:.2f} fy={pair.calib.K[1, 1]:.2f} cx={pair.calib.K[0, 2]:.2f} "
        f"cy={pair.calib.K[1, 2]:.2f}, baseline {pair.calib.baseline:g} m, doffs {pair.calib.doffs:g} px")
    left, right = pair.left.to(device), pair.right.to(device)
    K = torch.as_tensor(pair.calib.K, dtype=torch.float32, device=device)[None]
    baseline = torch.tensor([pair.calib.baseline], dtype=torch.float32, device=device)

    with torch.no_grad():
        gaussians = None
        if args.checkpoint:
            extra = {"doffs": pair.calib.doffs} if pair.calib.doffs else {}
            gaussians, z = predictor.predict(left, right, K, baseline, **extra)
            timer.lap("predict")
        else:
            disparity = encoder(left, right).disparity
            z = depth_from_disparity(disparity, K[:, 0, 0], baseline, doffs=pair.calib.doffs)
            timer.lap("encoder")
            if args.method == "naive-gs":
                gaussians = baselines.naive_gs(left, z, K)
                timer.lap("compose")

        out = Path(args.out)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.resolve().parent))
        try:
            (tmp / "views").mkdir()
            if gaussians is not None:
                raw = gaussians if pair.rectification is None else pair.rectification.to_raw_frame(gaussians)
                export.write_ply(raw, tmp / "scene.ply")
            zc = z[0, 0].cpu().numpy()
            matched = zc[zc < Z_MAX] if (zc < Z_MAX).any() else zc.ravel()   # z_max marks "no match"
            near, far = np.percentile(matched, 2), np.percentile(matched, 98)
            (tmp / "depth.png").write_bytes(encode_png(export.depth_png(zc, near, far)))
            timer.lap("export")

            focus = float(np.median(matched))
            named = export.novel_view_cameras(VIEW_RADIUS * focus, focus)
            orbit = export.orbit_cameras(ORBIT_FRAMES, VIEW_RADIUS * focus, focus)
            viewmats = torch.as_tensor(np.concatenate([np.stack(list(named.values())), orbit]),
                                       dtype=torch.float32, device=device)[None]
            Ks = K[:, None].expand(1, viewmats.shape[1], 3, 3).contiguous()
            if gaussians is not None:
                rgb, _ = render_views(gaussians, viewmats, Ks, w, h)
            else:
                rgb, _ = baselines.forward_splat(left, z, K, viewmats, Ks, w, h)
            frames = to_uint8(rgb[0].permute(0, 2, 3, 1).cpu().numpy())
            for i, name in enumerate(named):
                (tmp / "views" / f"{name}.png").write_bytes(encode_png(frames[i]))
            export.write_orbit_gif(frames[len(named):], tmp / "orbit.gif")
            timer.lap("render views")
            written = _move_into(tmp, out)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    log(timer.table())
    log(check.summary())
    log(f"wrote {out}/: " + ", ".join(written))


def _move_into(tmp: Path, out: Path) -> list[str]:
    """Move every file of ``tmp`` into ``out`` (same file system, one ``os.replace`` each); their names."""
    written = []
    for src in sorted(tmp.rglob("*")):
        dst = out / src.relative_to(tmp)
        if src.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
            written.append(str(src.relative_to(tmp)))
    return written


def run(args: argparse.Namespace) -> int:
    """Entry point of the CLI: 0 on success; 2 with one message on stderr for bad input."""
    from .weights import WeightsError

    try:
        predict(args)
    except (PredictError, CalibError, stereo_check.StereoCheckError, WeightsError, EncoderFlagError) as e:
        print(f"sgmodel predict: error: {e}", file=sys.stderr)
        return 2
    return 0
