"""``sgmodel predict``: from a user's rectified stereo pair, or a stereo video, to 3DGS scenes in the left
camera's frame (OpenCV axes: x right, y down, z forward; metres).

A pair (``--left L --right R``) writes ``OUT/scene.<format>`` (``--format ply`` (default, INRIA),
``compressed-ply``, ``spz`` or ``sog``; SH degree as the content has it: 0 for naive-GS), ``OUT/settings.json``
(SuperSplat viewer camera at the left camera) and ``OUT/cameras.json`` (the same camera, INRIA layout),
``OUT/depth.png`` (turbo colour map of the z-depth, red near, blue far, black without a stereo depth),
``OUT/views/*.png`` (novel views around the left camera) and ``OUT/orbit.gif``. ``--method forward-splat``
has no Gaussians: no scene or viewer files, its views are the z-buffered warp of the left image.

A stereo video (``--video SBS`` side by side, or ``--left-video L --right-video R``; ``sgmodel.predict.video``)
writes ``OUT/novel_view.<mp4|avi|mkv>`` (``--codec``), the novel view of every frame along ``--trajectory``,
the viewer files, and with ``--frames`` ``OUT/frames/NNNNNN.<format>`` (default compressed-ply), one scene per frame.

Pixels without a valid stereo depth (no match, occluded, outside the encoder's range, beyond the depth
clamps) produce no Gaussian; the log says how many were dropped. Images (frames) are resized so the short
side is the model's resolution (the checkpoint's, or ``--resolution``, or 256 for the baselines), keeping
the aspect ratio, each side rounded to a multiple of 16; K (and doffs) are scaled to match, and the
outputs are at that size. Images are turned upright by their EXIF Orientation tag (as OpenCV's ``imread``
does; the calibration is of the upright pixels).

Every input is checked before anything is written: the images (readable, one size, at least 16 pixels a
side), the calibration against them (principal point inside the image; a warning when it is far from the
centre, as with a K of another resolution), a pair's depth against the calibration (refused when ``doffs``
or the baseline puts 99% of the pixels at the depth clamp), and OUT (absent, empty, or an earlier output of
``sgmodel predict``; apart from the inputs). The outputs are written to a staging folder beside OUT that
replaces OUT as a whole at the end (``scenesplat_stereo.common.ownership.StagedFolder``): no file of an earlier
prediction is left beside new ones, and Ctrl-C leaves OUT as it was (one line, exit 130). Errors in the inputs
raise ``PredictError`` (or ``CalibError``, a ``StereoCheckError``), which the command line turns into one line
and exit status 2.

With ``--rig`` the pair (or every video frame) is raw: it is rectified first (``sgmodel.pairs.rectify``, the pair
transform of ``sgmodel.pairs.prepare``), the scene files are then in the raw left camera's frame (the viewer files
hold the rectified left camera in that frame), while ``depth.png`` and the views stay images of the rectified
left camera (the model's input). Before the model runs, ``sgmodel.pairs.stereo_check`` measures the pair's (the
first frame's) vertical disparity and the sign of its disparity and warns (``--strict``: exit 2); the
summary repeats its figures.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.common.commandline import Interrupted
from scenesplat_stereo.common.measure import synced_clock
from scenesplat_stereo.common.ownership import StagedFolder, check_apart, check_replaceable
from scenesplat_stereo.scene.scene_files import FORMATS
from scenesplat_stereo.shards.encode import encode_png, to_uint8
from sgmodel.args import add_device_argument, add_precision_argument, device_from_flag
from sgmodel.encoders import DEFAULT_ENCODER
from sgmodel.encoders.flags import add_encoder_arguments, build_encoder, merge_encoder
from sgmodel.metrics.sheets import depth_png
from sgmodel.model import baselines
from sgmodel.model.geometry import Z_MAX, Z_MIN
from sgmodel.pairs import rig, stereo_check
from sgmodel.pairs.calib import Calibration
from sgmodel.pairs.prepare import prepare_pairs, read_calibration, read_pair, rectify_pair
from sgmodel.pairs.stereo_pair import SIZE_MULTIPLE, Pair, PredictError, model_size, to_tensor
from sgmodel.predict import export, video
from sgmodel.predict.inference import Reconstructor
from sgmodel.predict.scene_writers import write_scene
from sgmodel.predict.viewers import write_viewer_files
from sgmodel.weights import SHIPPED, checkpoint_path, describe_checkpoint

#: Short side the baselines run at when neither a checkpoint nor --resolution says (SPEC section 7, S).
DEFAULT_RESOLUTION = 256
#: Novel views sit this fraction of the median valid depth away from the left camera.
VIEW_RADIUS = 0.15
#: Frames in the orbit animation.
ORBIT_FRAMES = 24
#: Scene format of a still pair and of video frames when --format is not given. Video frames: the compact format
#: whose writers keep up with a 448x256 video at 30 frames/s on a 16-core GPU host (the shipped model's SH-2
#: scenes: 40.1-42.4 frames/s, 4.2x smaller than .ply; .spz 24-25, SOG 16-21: docs/benchmarks.md "Issue 35: the
#: shipped model's scenes per frame").
DEFAULT_FORMAT, DEFAULT_FRAME_FORMAT = "ply", "compressed-ply"
#: Pairs per model call in a video.
DEFAULT_BATCH = 4
DEFAULT_CODEC = "mp4v"  # the novel-view video of --video
#: Fraction of a pair's pixels at the depth clamp from which its depth is refused (doffs or baseline wrong);
#: from half of them on, a warning.
CLAMPED_REFUSED, CLAMPED_WARNED = 0.99, 0.5
OWNER = "sgmodel predict"  # recorded in OUT (ownership.OWNER_FILE): a later prediction may replace OUT
logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``sgmodel predict``."""
    inputs = parser.add_argument_group("input: a rectified pair (raw with --rig), or a stereo video")
    inputs.add_argument("--left", help="left (reference) image of a rectified pair (raw with --rig)")
    inputs.add_argument("--right", help="right image, same size as the left")
    inputs.add_argument("--video", help="side-by-side stereo video (left eye in the left half)")
    inputs.add_argument("--left-video", help="left video of a stereo pair of videos (with --right-video)")
    inputs.add_argument("--right-video", help="right video: same size, frame rate and length as --left-video")
    parser.add_argument("--calib", help="FoundationStereo K.txt (K row-major; baseline in metres) or "
                        "Middlebury 2014 calib.txt, of one eye's image")
    parser.add_argument("--intrinsics", help="fx,fy,cx,cy in pixels of the input images (instead of --calib)")
    parser.add_argument("--baseline", help="baseline in metres (with --intrinsics)")
    rig.add_arguments(parser)
    stereo_check.add_arguments(parser)
    parser.add_argument("--checkpoint", help=f"a trained model checkpoint, or {SHIPPED.name!r}: the model shipped in the "
                        "package (the default when neither --checkpoint nor --method is given)")
    parser.add_argument("--method", choices=baselines.METHODS,
                        help="a baseline without learned prediction instead of the model")
    add_precision_argument(parser)
    parser.add_argument("--out", required=True, help="output folder (created; existing files replaced)")
    parser.add_argument("--format", choices=sorted(FORMATS),
                        help=f"scene file format (default {DEFAULT_FORMAT} for a pair, {DEFAULT_FRAME_FORMAT} for "
                        "--frames): " + "; ".join(f"{n} = {f.description}" for n, f in FORMATS.items()))
    add_encoder_arguments(parser, f"the checkpoint's; {DEFAULT_ENCODER} for --method")
    parser.add_argument("--resolution", type=int, help="short side the model runs at (default: the "
                        f"checkpoint's; {DEFAULT_RESOLUTION} for --method)")
    add_device_argument(parser)
    vid = parser.add_argument_group("video")
    vid.add_argument("--trajectory", help="novel view of each frame: offset:dx,dy,dz (metres "
                     "from the left camera, its axes, not turned) or orbit[:radius[,seconds]] (default: radius "
                     f"{video.ORBIT_RADIUS} x the first frame's median depth, {video.ORBIT_PERIOD:g} s a turn)")
    vid.add_argument("--frames", action="store_true", help="also write one scene per frame (OUT/frames/)")
    vid.add_argument("--codec", choices=sorted(video.CODECS),
                     help="novel-view video: mp4v (.mp4, default), mjpg (.avi) or ffv1 (.mkv, lossless)")
    vid.add_argument("--batch-size", type=int,
                     help=f"pairs per model call (default {DEFAULT_BATCH})")
    vid.add_argument("--max-frames", type=int, help="stop after this many frames")
    vid.add_argument("--no-progress", action="store_true", help="no progress bar")


def make_encoder(name: str | None, weights: str | None, repo: str | None, device: str):
    """The frozen stereo encoder of the baselines (``sgmodel.encoders``; its default when name is None)."""
    return build_encoder(merge_encoder(None, name, weights, repo), device)


def make_reconstructor(args: argparse.Namespace, device: torch.device) -> tuple[Reconstructor, int]:
    """The model of ``--checkpoint`` (the shipped one without it) or the baseline of ``--method`` on its encoder,
    and the short side."""
    if not args.method:
        from sgmodel.model.network import load_predictor

        predictor = load_predictor(checkpoint_path(args.checkpoint), device, args.encoder_weights, args.encoder_repo,
                                   args.encoder, args.amp)
        return Reconstructor(predictor=predictor), args.resolution or predictor.resolution
    encoder = make_encoder(args.encoder, args.encoder_weights, args.encoder_repo, device)
    return Reconstructor(method=args.method, encoder=encoder), args.resolution or DEFAULT_RESOLUTION


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
    modes = [m for m, given in (("--left/--right", args.left or args.right), ("--video", args.video),
                                ("--left-video/--right-video", args.left_video or args.right_video)) if given]
    if len(modes) != 1:
        raise PredictError("give one input: --left L --right R, --video SBS, or --left-video L --right-video R"
                           + (f" (got {' and '.join(modes)})" if modes else ""))
    for a, b in (("left", "right"), ("left_video", "right_video")):
        if bool(getattr(args, a)) != bool(getattr(args, b)):
            missing = b if getattr(args, a) else a
            raise PredictError(f"--{missing.replace('_', '-')} is missing (--{a.replace('_', '-')} and "
                               f"--{b.replace('_', '-')} go together)")
    if args.checkpoint and args.method:
        raise PredictError("give --checkpoint CKPT or --method {naive-gs,forward-splat}, not both (with neither, "
                           f"the shipped model {SHIPPED.name!r} runs)")
    if args.checkpoint and args.checkpoint != SHIPPED.name and not Path(args.checkpoint).is_file():
        raise PredictError(f"--checkpoint {args.checkpoint}: file not found")
    if args.resolution is not None and args.resolution < SIZE_MULTIPLE:
        raise PredictError(f"--resolution must be at least {SIZE_MULTIPLE}, got {args.resolution}")
    if args.method == "forward-splat" and (args.format or args.frames):
        raise PredictError("--format/--frames write Gaussians; --method forward-splat has none")
    if args.left:
        video_only = [f for f, given in (("--frames", args.frames), ("--max-frames", args.max_frames is not None),
                                         ("--trajectory", args.trajectory is not None), ("--codec", args.codec),
                                         ("--batch-size", args.batch_size is not None)) if given]
        if video_only:
            raise PredictError(f"{', '.join(video_only)}: for a video (--video or --left-video/--right-video); a "
                               f"still pair writes one scene and its views")
    elif args.format and not args.frames:
        raise PredictError(f"--format {args.format}: a video writes scene files only with --frames (OUT/frames/); add "
                           f"--frames, or leave --format out")
    args.trajectory, args.codec = args.trajectory or "orbit", args.codec or DEFAULT_CODEC
    args.batch_size = DEFAULT_BATCH if args.batch_size is None else args.batch_size
    if args.batch_size < 1 or (args.max_frames is not None and args.max_frames < 1):
        raise PredictError(f"--batch-size and --max-frames must be at least 1, got {args.batch_size} and "
                           f"{args.max_frames}")
    out = Path(args.out)
    if not out.resolve().parent.is_dir():
        raise PredictError(f"--out {args.out}: parent folder {out.resolve().parent} does not exist")
    inputs = ("--left", "--right", "--video", "--left-video", "--right-video", "--calib", "--rig")
    paths = {f: getattr(args, f[2:].replace("-", "_")) for f in inputs}
    paths["--checkpoint"] = None if args.method else checkpoint_path(args.checkpoint)
    check_apart(out, "--out", paths, replaced=True)
    check_replaceable(out, "--out", OWNER)


def check_depth(z: torch.Tensor, calib: Calibration) -> None:
    """PredictError when (nearly) every pixel's depth z [1,1,H,W] is at a clamp, z_max or z_min: a ``doffs`` or
    baseline that does not fit the pair (the numbers in the message); a warning when most are."""
    clamped = ((z >= Z_MAX) | (z <= Z_MIN)).float().mean().item()
    if clamped < CLAMPED_WARNED:
        return
    text = (f"{calib.source}: {100 * clamped:.1f}% of the pixels get a depth at the clamp ({Z_MIN:g} or {Z_MAX:g} m) "
            f"with fx={calib.K[0, 0]:.1f} px, baseline {calib.baseline:g} m, doffs {calib.doffs:g} px (z = fx B / "
            f"(d + doffs); d + doffs <= 0 is 'no match'): check doffs (Middlebury: cx1 - cx0, pixels) and the "
            f"baseline; or the images do not match (the same image twice?) or the scene lies outside the model's "
            f"depth range")
    if clamped >= CLAMPED_REFUSED:
        raise PredictError(text)
    logger.warning(text)


def predict(args: argparse.Namespace, log=print) -> None:
    """Do the work of ``sgmodel predict`` (raises PredictError / CalibError / StereoCheckError on bad input)."""
    _check_args(args)
    trajectory = video.parse_trajectory(args.trajectory)
    device = torch.device(device_from_flag(args.device))
    timer = _Timer(device)
    source = None
    try:
        if args.left:
            first = rectify_pair(read_pair(args))
        else:
            source = video.StereoSource(args.video or args.left_video, args.right_video)
            name = f"--video {args.video}" if args.video else f"--left-video {args.left_video}"
            calib, rectification = read_calibration(args, source.width, source.height, name)
            first = rectify_pair(Pair(*(to_tensor(x) for x in source.first_frames()), calib, rectification))
        if first.rectification is not None:
            timer.lap("read and rectify")
            first.rectification.report(log)
        reconstructor, short = make_reconstructor(args, device)
        log(f"model: {describe_checkpoint(args.checkpoint)}, {reconstructor.predictor.precision(device)}"
            if not args.method else f"method: {args.method}")
        timer.lap("load")
        check = stereo_check.run_check(first.left, first.right, args.strict, first.calib.doffs,
                                       first.rectification is not None, log)
        timer.lap("stereo check")
        out = Path(args.out)
        with StagedFolder(out, OWNER) as tmp:  # replaces OUT as a whole, or leaves it as it was
            if source is None:
                _predict_pair(args, first, reconstructor, short, device, timer, tmp, log)
            else:
                _predict_video(args, source, first, reconstructor, short, trajectory, device, tmp, log)
            written = sorted(str(p.relative_to(tmp)) for p in tmp.rglob("*") if p.is_file())
    except KeyboardInterrupt:
        raise Interrupted(f"--out {args.out} is as it was (a prediction replaces it only when complete); rerun "
                          f"the same command") from None
    finally:
        if source is not None:
            source.close()
    if source is None:
        log(timer.table())
    log(check.summary())
    log(f"wrote {out}/: " + ", ".join(written if len(written) <= 12 else written[:11] + ["..."]))


def _log_model_size(pair: Pair, short: int, log) -> None:
    h, w = pair.left.shape[-2:]
    K = pair.calib.K
    log(f"model size {w}x{h} (short side {short}, sides multiples of {SIZE_MULTIPLE}); K scaled to "
        f"fx={K[0, 0]:.2f} fy={K[1, 1]:.2f} cx={K[0, 2]:.2f} cy={K[1, 2]:.2f}, baseline {pair.calib.baseline:g} m, "
        f"doffs {pair.calib.doffs:g} px")


def _log_dropped(kept: int, produced: int, what: str, log) -> None:
    log(f"{produced - kept:,} of {produced:,} {what} dropped: no valid stereo depth (no match, occluded, outside "
        f"the encoder's range or the depth clamps); {kept:,} kept")


def _scene_frame(pair: Pair) -> tuple[Callable | None, np.ndarray]:
    """What the scene files are in: with ``--rig`` the raw left camera's frame (the Gaussians turned back by
    ``Rectification.to_raw_frame``), else the left camera's. Returns that move (None: none) and the model's
    (rectified) left camera in it, c2w [4,4], for the viewer files."""
    c2w = np.eye(4)
    if pair.rectification is None:
        return None, c2w
    c2w[:3, :3] = pair.rectification.R1.T  # p_rect = R1 p_raw: the rectified camera's axes in the raw frame
    return pair.rectification.to_raw_frame, c2w


def _predict_pair(args, raw: Pair, reconstructor: Reconstructor, short: int, device, timer: _Timer, tmp: Path,
                  log) -> None:
    pair = prepare_pairs(short)(raw)
    _log_model_size(pair, short, log)
    _, _, h, w = pair.left.shape
    left, right, K, baseline = pair.model_inputs(device)
    timer.lap("model size")
    scenes = reconstructor(left, right, K, baseline, pair.calib.doffs, lap=timer.lap)
    check_depth(scenes.depth[:1], pair.calib)
    kept, produced = scenes.counts(0)
    _log_dropped(kept, produced, "Gaussians" if scenes.gaussians is not None else "pixels", log)
    (tmp / "views").mkdir()
    focus = scenes.focus(0)
    if scenes.gaussians is not None:
        frame, c2w = _scene_frame(pair)
        scene = scenes.in_frame(frame).scene(0)
        timer.lap("scene to host")
        fmt = args.format or DEFAULT_FORMAT
        write_scene(scene, tmp / f"scene{FORMATS[fmt].suffix}", fmt)
        timer.lap(f"export {fmt}")
        log(f"scene: {len(scene):,} Gaussians, SH degree {scene.sh_degree}"
            + (", in the raw left camera's frame" if frame is not None else ""))
        write_viewer_files(tmp, pair.calib.K, w, h, focus, c2w)
    z, valid = scenes.depth[0, 0].cpu().numpy(), scenes.pixel_valid[0, 0].cpu().numpy()
    (tmp / "depth.png").write_bytes(encode_png(depth_png(z, valid=valid)))
    timer.lap("depth and viewer files")
    named = export.novel_view_cameras(VIEW_RADIUS * focus, focus)
    orbit = export.orbit_cameras(ORBIT_FRAMES, VIEW_RADIUS * focus, focus)
    viewmats = torch.as_tensor(np.concatenate([np.stack(list(named.values())), orbit]),
                               dtype=torch.float32, device=device)[None]
    rgb = scenes.render(viewmats, K[:, None].expand(1, viewmats.shape[1], 3, 3).contiguous(), w, h)
    frames = to_uint8(rgb[0].permute(0, 2, 3, 1).cpu().numpy())
    for i, name in enumerate(named):
        (tmp / "views" / f"{name}.png").write_bytes(encode_png(frames[i]))
    export.write_orbit_gif(frames[len(named):], tmp / "orbit.gif")
    timer.lap("render views")


def _predict_video(args, source: video.StereoSource, first: Pair, reconstructor: Reconstructor, short: int,
                   trajectory: video.Trajectory, device, tmp: Path, log) -> None:
    fmt = args.format or DEFAULT_FRAME_FORMAT
    codec = video.CODECS[args.codec]
    prepare = prepare_pairs(short)
    w, h = model_size(first.left.shape[-1], first.left.shape[-2], short)  # the size every frame is resized to
    frames = tmp / "frames" if args.frames else None
    if frames is not None:
        frames.mkdir()
    log(f"{args.video or args.left_video}: {source.width}x{source.height} per eye, {source.fps:g} fps, "
        f"{source.frame_count or 'unknown'} frames; {reconstructor.name} at {w}x{h}, batches of {args.batch_size}")
    frame, c2w = _scene_frame(first)
    sink = video.VideoSink(tmp / f"novel_view{codec.suffix}", args.codec, source.fps, w, h, frames, fmt, frame,
                           device=device)

    def on_first(pair: Pair, focus: float) -> None:
        _log_model_size(pair, short, log)
        if reconstructor.method != "forward-splat":
            write_viewer_files(tmp, pair.calib.K, w, h, focus, c2w)

    report = video.stream(source, first.calib, first.rectification, prepare, reconstructor, trajectory, sink, device,
                          args.batch_size, args.max_frames, not args.no_progress, on_first=on_first)
    if not report.frames:
        raise PredictError(f"{args.video or args.left_video}: no frame could be decoded")
    _log_dropped(report.kept, report.produced,
                 "pixels" if reconstructor.method == "forward-splat" else "Gaussians (all frames)", log)
    log(report.table((w, h)))


def run(args: argparse.Namespace) -> int:
    """Entry point of the CLI: 0 on success (bad input raises; the command line makes it one line, exit 2)."""
    predict(args)
    return 0
