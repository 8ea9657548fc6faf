"""Stereo video to a rendered novel-view video (and one scene per frame): ``sgmodel predict --video``.

    decode -> batches of raw ``Pair`` s -> the pair transform (``sgmodel.pairs.prepare``; both in the reader
    thread) -> ``inference.Reconstructor`` (the path of a still pair) -> one novel view per frame -> encode
    (writer thread)
    and, with ``--frames``, each frame's scene to the host (``SCENE_WRITERS`` threads) and its file
    (``SCENE_WRITERS`` writer processes, ``scene_writers.SceneWriters``)

Input: one side-by-side video (left eye in the left half) or a left and a right video of one size and frame
rate, with the calibration of one eye's frame (as for a still pair). Output: the novel view of every frame
from a camera on a trajectory (``Trajectory``) at the model's size, and with ``--frames`` each frame's
Gaussians as a scene file (the left camera frame of that frame).

Video I/O is OpenCV's (``cv2.VideoCapture`` / ``cv2.VideoWriter``, the FFmpeg its wheel bundles): already a
dependency, and both calls release the GIL, so decoding and encoding run in threads beside the model. PyAV
would add a dependency for one thing OpenCV's wheel lacks, an H.264 encoder; the encoders that work in
opencv-contrib-python-headless here are in ``CODECS`` (checked by tests/sgmodel/predict/test_video.py), and an ``.mp4``
of mp4v plays in browsers and players or converts with ``ffmpeg -i novel_view.mp4 -c:v libx264 out.mp4``.
"""

from __future__ import annotations

import math
import re
import statistics
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from scenesplat_stereo.common.measure import synced_clock
from scenesplat_stereo.scene import row_tasks
from scenesplat_stereo.scene.gaussians import GaussianScene
from scenesplat_stereo.scene.scene_files import FORMATS
from scenesplat_stereo.shards.encode import to_uint8
from sgmodel.pairs.calib import Calibration
from sgmodel.pairs.prepare import PairTransform
from sgmodel.pairs.rectify import Rectification
from sgmodel.pairs.stereo_pair import Pair, PredictError, to_tensor
from sgmodel.predict.export import offset_camera, orbit_camera
from sgmodel.predict.inference import Reconstructor
from sgmodel.predict.scene_writers import QUANTISED_ON_DEVICE, SceneWriters, write_scene


@dataclass(frozen=True)
class Codec:
    """An encoder OpenCV's wheel can write: FourCC, the container's suffix, whether it is lossless."""

    fourcc: str
    suffix: str
    lossless: bool


#: ``--codec`` choices (each written and read back by tests/sgmodel/predict/test_video.py).
CODECS = {"mp4v": Codec("mp4v", ".mp4", False), "mjpg": Codec("MJPG", ".avi", False),
          "ffv1": Codec("FFV1", ".mkv", True)}
#: Frame rate written when the input does not state one.
DEFAULT_FPS = 30.0
#: The orbit's default radius (a fraction of the first frame's median depth) and its period in seconds.
ORBIT_RADIUS, ORBIT_PERIOD = 0.15, 8.0
#: Batches queued for the writer threads at most: the model waits beyond that (frames and scenes held in memory).
MAX_QUEUED = 2
#: Processes writing the per-frame scenes of ``--frames`` (and threads copying them to the host): the usable cores
#: but 4 (the model's thread, the reader, the encoder and one spare), 2 to 12. A compact writer takes longer than
#: a frame's prediction (a .spz's deflate alone 100-250 ms a 200K-Gaussian scene), so several write side by side.
SCENE_WRITERS = max(2, min(12, row_tasks.workers() - 4))
#: torch's CPU threads in this process while a stream runs on a GPU (the pair transform of a batch needs few, and
#: idle OpenMP threads spin between parallel regions: 16 of them took some 4.3 of a 16-core host's cores beside the
#: 12 writer processes), except while SOG scenes are quantised in this process (there 4 threads measured slower).
#: docs/benchmarks.md "Issue 35: the shipped model's scenes per frame".
GPU_STREAM_CPU_THREADS = 4


# ---------------------------------------------------------------- input

class StereoSource:
    """Frames of a side-by-side video (``right`` None) or of a left and a right video, decoded to RGB."""

    def __init__(self, left: str, right: str | None = None) -> None:
        self.paths = [left] if right is None else [left, right]
        flags = ["--video"] if right is None else ["--left-video", "--right-video"]
        self.captures = []
        try:
            self._open(left, right, flags)
        except PredictError:
            self.close()
            raise

    def _open(self, left: str, right: str | None, flags: list[str]) -> None:
        """Open every path into ``self.captures``, decode and check the first frames, set the sizes."""
        first = []
        for path, flag in zip(self.paths, flags):
            if not Path(path).is_file():
                raise PredictError(f"{flag} {path}: file not found")
            cap = cv2.VideoCapture(str(path))
            self.captures.append(cap)
            ok, frame = cap.read() if cap.isOpened() else (False, None)
            if not ok:
                raise PredictError(f"{flag} {path}: not a video OpenCV can decode")
            first.append(frame)
        shapes = [f.shape for f in first]
        fps = [c.get(cv2.CAP_PROP_FPS) for c in self.captures]
        counts = [int(c.get(cv2.CAP_PROP_FRAME_COUNT)) for c in self.captures]
        if right is None and shapes[0][1] % 2:
            raise PredictError(f"--video {left}: a side-by-side video has an even width, got {shapes[0][1]}")
        if right is not None and (shapes[0] != shapes[1] or abs(fps[0] - fps[1]) > 1e-3 or counts[0] != counts[1]):
            raise PredictError(f"--left-video {left} is {shapes[0][1]}x{shapes[0][0]}, {fps[0]:g} fps, {counts[0]} "
                               f"frames but --right-video {right} is {shapes[1][1]}x{shapes[1][0]}, {fps[1]:g} fps, "
                               f"{counts[1]} frames: a stereo pair of videos has one size, rate and length")
        self.height = shapes[0][0]
        self.width = shapes[0][1] // 2 if right is None else shapes[0][1]
        self.fps = fps[0] if fps[0] > 0 else DEFAULT_FPS
        self.frame_count = counts[0] if counts[0] > 0 else None
        self._first, self._first_pending = first, True  # decoded to check the input; the first read returns it

    def _split(self, frames: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """One decoded frame per capture (BGR) -> (left, right) RGB [H,W,3]."""
        rgb = [f[..., ::-1] for f in frames]
        return (rgb[0][:, :self.width], rgb[0][:, self.width:]) if len(rgb) == 1 else (rgb[0], rgb[1])

    def first_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """The first frame's (left, right) uint8 RGB [H,W,3], without consuming it (for the stereo check)."""
        return self._split(self._first)

    def read(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Up to n next frames: (left, right) uint8 RGB [m,H,W,3], m < n only at the end of the video."""
        lefts, rights = [], []
        for _ in range(n):
            if self._first_pending:
                frames, self._first_pending = self._first, False
            else:
                read = [cap.read() for cap in self.captures]
                if not all(ok for ok, _ in read):
                    break
                frames = [f for _, f in read]
            left, right = self._split(frames)
            lefts.append(left)
            rights.append(right)
        empty = np.zeros((0, self.height, self.width, 3), np.uint8)
        return (np.stack(lefts), np.stack(rights)) if lefts else (empty, empty)

    def close(self) -> None:
        for cap in self.captures:
            cap.release()
        self.captures = []


# ---------------------------------------------------------------- trajectory

@dataclass(frozen=True)
class Trajectory:
    """Where the novel view of frame f is seen from, in that frame's left camera (OpenCV axes, metres):
    ``offset``: the left camera moved by (dx, dy, dz), not turned; ``orbit``: a circle of ``radius`` metres
    (None: ORBIT_RADIUS x the first frame's median depth) around the left camera centre in its image plane,
    one turn per ``period`` seconds of video, looking at the first frame's median depth on the axis."""

    kind: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float | None = None
    period: float = ORBIT_PERIOD

    def viewmat(self, frame: int, fps: float, focus: float) -> np.ndarray:
        """World(= left camera)-to-novel-view [4,4] for frame number ``frame``."""
        if self.kind == "offset":
            return offset_camera(np.array(self.offset))
        radius = ORBIT_RADIUS * focus if self.radius is None else self.radius
        return orbit_camera(2 * math.pi * frame / (fps * self.period), radius, focus)


def parse_trajectory(text: str) -> Trajectory:
    """``offset:dx,dy,dz`` (metres) or ``orbit``, ``orbit:RADIUS`` or ``orbit:RADIUS,SECONDS``."""
    number = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
    if m := re.fullmatch(rf"offset:({number}),({number}),({number})", text):
        return Trajectory("offset", offset=tuple(float(x) for x in m.groups()))
    if m := re.fullmatch(rf"orbit(?::({number})(?:,({number}))?)?", text):
        radius, period = (float(x) if x is not None else None for x in m.groups())
        if (radius is not None and radius <= 0) or (period is not None and period <= 0):
            raise PredictError(f"--trajectory {text!r}: the orbit's radius and period must be positive")
        return Trajectory("orbit", radius=radius, period=ORBIT_PERIOD if period is None else period)
    raise PredictError(f"--trajectory {text!r}: expected offset:dx,dy,dz (metres) or orbit[:radius[,seconds]]")


# ---------------------------------------------------------------- output

class VideoSink:
    """The novel-view video (``codec`` of CODECS at ``fps``, width x height) and, when ``scene_folder`` is
    given, one scene per frame named by frame number, its Gaussians moved by ``scene_frame`` first (a raw
    rig's left camera frame; None: the model's).

    The frames are encoded in order by one writer thread; each scene is copied to the host by one of
    ``scene_writers`` threads and written by one of as many processes (each file atomically,
    ``scene_writers.write_scene``), so a format whose writer takes longer than a frame's prediction still keeps
    up: the stream runs at the rate of the slower of the model and ``scene_writers`` writers, not of their sum.
    With the model on a GPU (``device``), each copying thread works on a CUDA stream of its own, which waits for
    its batch's Gaussians (an event recorded by ``submit``) and not for the model's later batches, and copies through
    page-locked memory (``export.to_scene``): on the model's stream, the copies of 276,480 Gaussians at SH 2
    (42 MB a frame) queued behind the model and held a 448x256 stream to 14-19 frames/s. A format of
    ``scene_writers.QUANTISED_ON_DEVICE`` (SOG) is also quantised there by the copying thread, and only encoded and
    written in the process. The batch's Gaussians are kept (the ``scene`` callable holds them) until every thread
    that reads them has waited for its stream, so the model's stream never reuses their memory too early.
    A batch counts as written when its frames and all its scenes are; the first error of a scene writer is raised
    from the batch's future, once (``close`` then drops the batches not yet started)."""

    def __init__(self, path: Path, codec: str, fps: float, width: int, height: int,
                 scene_folder: Path | None = None, scene_format: str = "spz",
                 scene_frame: Callable[[dict], dict] | None = None, scene_writers: int = SCENE_WRITERS,
                 device: torch.device | None = None) -> None:
        self.writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*CODECS[codec].fourcc), fps, (width, height))
        if not self.writer.isOpened():
            raise PredictError(f"--codec {codec}: OpenCV cannot write {CODECS[codec].fourcc} to {path.name}")
        self.scene_folder, self.scene_format, self.scene_frame = scene_folder, scene_format, scene_frame
        self.quantise_on = device if device is not None and device.type == "cuda" else None
        quantising = scene_folder is not None and scene_format in QUANTISED_ON_DEVICE
        #: torch's CPU threads for the stream (None: as they are).
        self.cpu_threads = GPU_STREAM_CPU_THREADS if self.quantise_on is not None and not quantising else None
        self._streams = threading.local()  # each copying thread's CUDA stream
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="video-writer")
        self.scene_writers = max(1, scene_writers)
        self.scene_pool = ThreadPoolExecutor(self.scene_writers, thread_name_prefix="scene-writer")
        try:
            self.processes = None if scene_folder is None else SceneWriters(self.scene_writers)
        except BaseException:
            self.writer.release()
            raise

    def submit(self, first: int, frames: np.ndarray, scene: Callable[[int], GaussianScene] | None = None) -> Future:
        """Queue uint8 RGB frames [n,H,W,3] (frame numbers first..) and, with a scene folder, their scenes:
        ``scene(i)`` makes frame first + i's (called in a scene writer, so the copy of its Gaussians to the
        host overlaps the model too). The future's result is the time the batch was written (perf_counter
        seconds)."""
        ready = None
        if self.scene_folder is not None and self.quantise_on is not None and self.quantise_on.type == "cuda":
            ready = torch.cuda.Event()
            ready.record(torch.cuda.current_stream(self.quantise_on))
        written = [] if self.scene_folder is None else \
            [self.scene_pool.submit(self._write_scene, scene, i, first + i, ready) for i in range(len(frames))]
        return self.pool.submit(self._write, frames, written)

    def _write_scene(self, scene: Callable[[int], GaussianScene], i: int, number: int,
                     ready: torch.cuda.Event | None) -> Path:
        path = self.scene_folder / f"{number:06d}{FORMATS[self.scene_format].suffix}"
        stream = None  # (torch.cuda.stream(None) changes nothing)
        if ready is not None:
            if not hasattr(self._streams, "stream"):
                self._streams.stream = torch.cuda.Stream(self.quantise_on)
            stream = self._streams.stream
            stream.wait_event(ready)
        with torch.cuda.stream(stream):
            return self.processes.write(scene(i), path, self.scene_format, write_scene, self.quantise_on)

    def _write(self, frames: np.ndarray, scenes: list[Future]) -> float:
        for f in frames:
            self.writer.write(np.ascontiguousarray(f[..., ::-1]))
        for future in scenes:
            future.result()
        return time.perf_counter()

    def close(self, cancel: bool = False) -> None:
        """Wait for the queued writes (``cancel``: only for those already started, after an error or Ctrl-C),
        then close the video."""
        self.scene_pool.shutdown(wait=True, cancel_futures=cancel)
        self.pool.shutdown(wait=True, cancel_futures=cancel)
        self.writer.release()
        if self.processes is not None:
            self.processes.close()


# ---------------------------------------------------------------- the stream

@dataclass
class BatchTimes:
    """One batch's frames and times (perf_counter seconds): decode start and end and the pair transform's end
    (reader thread, ahead of the model), model start and end (prediction), render end (the frames on the host),
    written (encoded, writer thread, and its scenes written, scene writer threads)."""

    frames: int
    decode_start: float
    decode_end: float
    transform_end: float
    model_start: float
    model_end: float
    render_end: float
    written: float = 0.0

    @property
    def latency(self) -> float:
        """Seconds the batch's frames were worked on: decode and transform, then model start to written (the wait
        of model-ready frames for the model to finish the batch before, a read-ahead, is not counted)."""
        return (self.transform_end - self.decode_start) + (self.written - self.model_start)


@dataclass
class StreamReport:
    """What ``stream`` did: per-batch times, Gaussians kept and produced over all frames, the focus."""

    batches: list[BatchTimes] = field(default_factory=list)
    kept: int = 0
    produced: int = 0
    focus: float = 0.0
    wall: float = 0.0

    @property
    def frames(self) -> int:
        return sum(b.frames for b in self.batches)

    def table(self, size: tuple[int, int]) -> str:
        """The summary table (markdown) printed at the end of ``sgmodel predict --video``."""
        b = self.batches
        stage = lambda f: sum(f(x) for x in b)  # noqa: E731
        latency = [x.latency for x in b] or [0.0]
        rows = [("frames", f"{self.frames}"), ("batches", f"{len(b)}"), ("model size", f"{size[0]}x{size[1]}"),
                ("decode s", f"{stage(lambda x: x.decode_end - x.decode_start):.2f}"),
                ("pair transform s", f"{stage(lambda x: x.transform_end - x.decode_end):.2f}"),
                ("model s (prediction)", f"{stage(lambda x: x.model_end - x.model_start):.2f}"),
                ("render s", f"{stage(lambda x: x.render_end - x.model_end):.2f}"),
                ("wall s", f"{self.wall:.2f}"), ("frames/s end to end", f"{self.frames / max(self.wall, 1e-9):.2f}"),
                ("batch latency median / max ms", f"{1e3 * statistics.median(latency):.0f} / {1e3 * max(latency):.0f}"),
                ("Gaussians kept per frame",
                 f"{self.kept / max(self.frames, 1):,.0f} of {self.produced / max(self.frames, 1):,.0f}"),
                ("focus (first frame's median depth) m", f"{self.focus:.3f}")]
        return "\n".join(["| | |", "|---|---:|"] + [f"| {k} | {v} |" for k, v in rows])


def stream(source: StereoSource, calib: Calibration, rectification: Rectification | None, prepare: PairTransform,
           reconstructor: Reconstructor, trajectory: Trajectory, sink: VideoSink, device: torch.device,
           batch_size: int, max_frames: int | None = None, progress: bool = True,
           on_first: Callable[[Pair, float], None] | None = None) -> StreamReport:
    """Decode, predict, render and encode the whole video (module docstring): each batch of frames becomes a raw
    ``Pair`` (``calib``, and ``rectification`` for a raw rig's frames), ``prepare`` makes it model-ready (on the
    CPU, in the reader thread: beside the model's work on the batch before, where a batch of four 1920x1080 pairs
    took 0.29-0.38 s of the 2-core CPU machine), then it goes to ``device``. ``on_first(pair, focus)`` is called
    once with the first model-ready batch and the focus (e.g. to write the viewer files)."""
    now = synced_clock(device)
    total = min(x for x in (source.frame_count, max_frames) if x is not None) \
        if (source.frame_count or max_frames) else None
    report, pending, done, written = StreamReport(), [], 0, 0
    queued = max(MAX_QUEUED, -(-sink.scene_writers // batch_size) + 1)  # keep every scene writer busy
    reader = ThreadPoolExecutor(1, thread_name_prefix="video-reader")

    def read(n: int) -> tuple[tuple[float, float, float], int, Pair | None]:
        """((start, decoded, transformed) times, frames, the model-ready pair) of up to n next frames."""
        start = time.perf_counter()
        left, right = source.read(n)
        decoded = time.perf_counter()
        pair = prepare(Pair(to_tensor(left), to_tensor(right), calib, rectification)) if len(left) else None
        return (start, decoded, time.perf_counter()), len(left), pair

    start, finished, threads = time.perf_counter(), False, torch.get_num_threads()
    torch.set_num_threads(min(threads, sink.cpu_threads or threads))
    bar = tqdm(total=total, unit="frame", disable=not progress, desc="video", dynamic_ncols=True)
    try:
        ahead = reader.submit(read, batch_size if total is None else min(batch_size, total))
        while ahead is not None:
            (t0, t1, t2), n, pair = ahead.result()
            t_start = now()
            if n == 0:
                break
            rest = None if total is None else total - done - n
            ahead = reader.submit(read, batch_size if rest is None else min(batch_size, rest)) \
                if rest is None or rest > 0 else None
            left, right, K, baseline = pair.model_inputs(device)
            scenes = reconstructor(left, right, K, baseline, pair.calib.doffs)
            t_model = now()
            if not report.batches:
                report.focus = scenes.focus(0)
                if on_first is not None:
                    on_first(pair, report.focus)
            h, w = pair.left.shape[-2:]
            viewmats = torch.as_tensor(np.stack([trajectory.viewmat(done + i, source.fps, report.focus)
                                                 for i in range(n)]), dtype=torch.float32, device=device)[:, None]
            rgb = scenes.render(viewmats, K[:, None].contiguous(), w, h)
            frames = to_uint8(rgb[:, 0].permute(0, 2, 3, 1).cpu().numpy())
            t_render = time.perf_counter()
            kept, produced = scenes.counts()
            report.kept, report.produced = report.kept + kept, report.produced + produced
            report.batches.append(BatchTimes(n, t0, t1, t2, t_start, t_model, t_render))
            pending.append(sink.submit(done, frames, scenes.in_frame(sink.scene_frame).scene
                                       if sink.scene_folder is not None else None))
            done += n
            bar.update(n)
            while len(pending) - written > queued:  # back-pressure: the writers are behind
                report.batches[written].written, written = pending[written].result(), written + 1
        for batch, future in zip(report.batches[written:], pending[written:]):
            batch.written = future.result()
        finished = True
    finally:
        torch.set_num_threads(threads)
        bar.close()
        reader.shutdown(wait=True)
        sink.close(cancel=not finished)  # after an error or Ctrl-C: only the writes already started end
    report.wall = time.perf_counter() - start
    return report
