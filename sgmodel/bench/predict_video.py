"""``sgmodel bench predict --video``: a stereo stream's pairs per second and latency, model alone and end to end.

A synthetic side-by-side video (``--frames`` frames of one eye's ``--size``, a smooth texture panning by
one pixel a frame with a 4-pixel disparity; MPEG-4 part 2 in ``.mp4``, the codec OpenCV's wheel encodes)
goes through the path of ``sgmodel predict --video`` (``sgmodel.predict.video.stream``): decode and the pair
transform (reader thread), the model, one novel view per frame, encode (mp4v, writer thread).

* model alone: ``Reconstructor`` on a batch of ``--batch-size`` model-ready pairs already on the device
  (encoder to Gaussians, with their validity), synchronised; ``--repeats`` batches after ``--warmup``;
  pairs/s = batch size / median time, latency = a batch's time.
* end to end: the whole video through ``stream``; frames/s = frames / wall time, latency of a frame = its
  batch's decode and transform time plus the time from the batch's model start to the end of its encode (a frame
  waits for its batch; the wait of frames made ready ahead for the model to finish the batch before is not
  counted).
  Then again for each of ``--scene-formats`` with a scene per frame written as ``predict --video --frames``
  writes them (``--scene-writers`` processes beside the model; a batch is done when its scenes are written;
  the processes' start, before the stream, is timed apart); "writers busy" is the processes' summed write time
  over their number times the wall time (near 100%: the writers hold the stream back). "CPU ms a frame" is this
  process's CPU time (every thread's, not the writer processes') over the stream, per frame.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from scenesplat_stereo.common.measure import synced_clock
from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import markdown_table
from scenesplat_stereo.scene.scene_files import FORMATS
from scenesplat_stereo.shards.encode import to_uint8
from sgmodel.bench import describe, report, synthetic_pair
from sgmodel.model.network import Predictor
from sgmodel.pairs.calib import Calibration
from sgmodel.pairs.prepare import prepare_pairs
from sgmodel.pairs.stereo_pair import Pair, to_tensor
from sgmodel.predict.inference import Reconstructor
from sgmodel.predict.video import CODECS, StereoSource, Trajectory, VideoSink, stream

#: The novel view of the end-to-end run: the left camera moved 5 cm to the right.
OFFSET = (0.05, 0.0, 0.0)
COLUMNS = ["measure", "batch", "pairs/s", "latency median ms", "latency p99 ms", "CPU ms a frame (this process)"]


def write_synthetic_video(path: Path, width: int, height: int, frames: int, fps: float = 30.0) -> Calibration:
    """A side-by-side mp4v video of ``synthetic_pair`` panning one pixel a frame; its calibration."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*CODECS["mp4v"].fourcc), fps, (2 * width, height))
    for f in range(frames):
        left, right, K, baseline = synthetic_pair(width, height, torch.device("cpu"), shift=f)
        sbs = torch.cat([left, right], dim=-1)[0].permute(1, 2, 0).numpy()
        writer.write(np.ascontiguousarray(to_uint8(sbs)[..., ::-1]))
    writer.release()
    return Calibration(K[0].double().numpy(), float(baseline[0]), size=(width, height), source="synthetic")


def _rate(per_second: float) -> str:
    """Pairs per second, with two decimals below 10 (a CPU's rates) and one above."""
    return f"{per_second:.2f}" if per_second < 10 else f"{per_second:.1f}"


def _stats(seconds: list[float], per_call: int) -> list[str]:
    ms = 1e3 * np.asarray(seconds)
    return [_rate(per_call / np.median(seconds)), f"{np.median(ms):.1f}", f"{np.percentile(ms, 99):.1f}"]


def bench_video(args: argparse.Namespace, predictor: Predictor, device: torch.device, out: OwnedFile) -> int:
    width, height = args.size
    reconstructor, b = Reconstructor(predictor=predictor), args.batch_size
    prepare = prepare_pairs(min(width, height))
    now = synced_clock(device)
    with tempfile.TemporaryDirectory() as tmp:
        video = Path(tmp) / "sbs.mp4"
        calib = write_synthetic_video(video, width, height, args.frames)
        source = StereoSource(str(video))
        left, right = source.read(b)
        source.close()
        pair = prepare(Pair(to_tensor(left).to(device), to_tensor(right).to(device), calib))
        _, _, K, baseline = pair.model_inputs(device)
        model_times = []
        for i in range(args.warmup + args.repeats):
            t = now()
            reconstructor(pair.left, pair.right, K, baseline)
            if i >= args.warmup:
                model_times.append(now() - t)
        w, h = pair.left.shape[-1], pair.left.shape[-2]
        runs, busy, cpu, start_s = {}, {}, {}, None
        for fmt in [None, *args.scene_formats]:
            source = StereoSource(str(video))
            frames = None if fmt is None else Path(tmp) / f"frames_{fmt}"
            if frames is not None:
                frames.mkdir()
            started = time.perf_counter()
            sink = VideoSink(Path(tmp) / "novel_view.mp4", "mp4v", source.fps, w, h, frames, fmt or "spz",
                             scene_writers=args.scene_writers, device=device)
            start_s = time.perf_counter() - started if frames is not None else start_s
            cpu_start = time.process_time()
            try:
                runs[fmt] = stream(source, calib, None, prepare, reconstructor, Trajectory("offset", offset=OFFSET),
                                   sink, device, b, progress=False)
            finally:
                source.close()
            cpu[fmt] = (time.process_time() - cpu_start) / max(runs[fmt].frames, 1)
            if frames is not None:
                busy[fmt] = sink.processes.busy_s / (args.scene_writers * runs[fmt].wall)
    rows = [["model alone (encoder to Gaussians)", b, *_stats(model_times, b), ""]]
    for fmt, run in runs.items():
        latency = [x.latency for x in run.batches for _ in range(x.frames)]
        scenes = "" if fmt is None else (f", a {FORMATS[fmt].suffix} scene per frame, format {fmt} (writers busy "
                                         f"{busy[fmt]:.0%})")
        rows.append([f"end to end (decode, model, one novel view, encode{scenes})", b,
                     _rate(run.frames / run.wall), f"{1e3 * np.median(latency):.1f}",
                     f"{1e3 * np.percentile(latency, 99):.1f}", f"{1e3 * cpu[fmt]:.0f}"])
    result = runs[None]
    stages = {k: sum(getattr(x, e) - getattr(x, s) for x in result.batches) / result.frames * 1e3
              for k, s, e in (("decode", "decode_start", "decode_end"), ("transform", "decode_end", "transform_end"),
                              ("model", "model_start", "model_end"), ("render", "model_end", "render_end"))}
    report(f"Stereo video of {width}x{height} per eye on {describe(args, predictor, device)}, {result.frames} frames in batches of {b}; model alone: {args.repeats} batches after "
           f"{args.warmup} warm-up.\n\n"
           f"{markdown_table(COLUMNS, rows)}\n\n"
           f"End to end per frame: decode {stages['decode']:.1f} ms and pair transform {stages['transform']:.1f} ms "
           f"(reader thread), model {stages['model']:.1f} ms, "
           f"render {stages['render']:.1f} ms (main thread); encode in the writer thread, and the scenes (copy to "
           f"the host) in {args.scene_writers} threads and written in as many processes"
           + ("" if start_s is None else f" (started in {start_s:.1f} s before the stream, the last time)")
           + ".\n", out)
    return 0
