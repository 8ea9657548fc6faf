"""``scenesplat-stereo bench build``: what the dataset build costs in time.

A synthetic teacher (``demo.make_room`` with ``--gaussians`` Gaussians, SH degree ``--sh-degree``) is
rendered along ``demo.room_trajectory`` through the build's own pipeline (``render_pairs``: all 12 cameras
of ``--batch-pairs`` pairs per rasterisation call, host copies overlapped with the next call -> encoder
threads or processes -> ``ShardWriter`` into a temporary folder). Per configuration, after an untimed
warm-up run of the same pairs through the whole pipeline (kernels, pinned host buffers, the encoder pool
and its shared slots), ``--pairs`` pairs are timed ``--repeats`` times; the table reports the median
pairs/s with min-max and the spread ((max - min) / median), and, from the median run, renders/s and the
split: render (waiting for the rasteriser and the device-to-host copy, s), encode (summed over encoder
threads, worker-s), write (tar + marker, s), and how long the renderer waited for the encoders.

Rows: the base setting at each ``--sizes`` entry for each ``--jpeg-encoders`` x ``--encoder-modes``
entry (``nvjpeg``: JPEGs encoded on the GPU, the host encoders write the masks only); at the first size
and the first mode, JPEG quality ``--qualities``, then ``--with-depth`` and ``--effects`` on (off, they
are skipped code paths: the base row is the "off" cost), and with ``--gsplat`` the same pipeline rendering
with gsplat's ``rasterization`` (CUDA only). A second table measures encoder scaling (workers, each mode).
With ``nvjpeg``, a third table compares the two JPEG encoders on the same rendered images (ms per image
in calls of one batch, bytes, PSNR against the rendered pixels). Last, per JPEG encoder and mode, the
projected time of the paper's training set (appendix B: 174,621 ScanNetGS pairs at
616x456 and 149,196 ScanNetPPGS-V2 pairs at 1752x1168, 12 images each) on this device, from the medians of
the base rows at those sizes (or, for a size not measured, scaled by pixel count from the nearest measured
one, and labelled so).
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import os
import statistics
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.build.demo import make_room, room_trajectory
from scenesplat_stereo.build.effects import CameraEffects
from scenesplat_stereo.build.protocol import SamplePlan, plan_scene
from scenesplat_stereo.build.render_pairs import start_render, stream_samples
from scenesplat_stereo.build.settings import BuildSettings
from scenesplat_stereo.common.measure import psnr_from_mse, synced_clock
from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.scene.cameras import intrinsics_matrix
from scenesplat_stereo.scene.teachers import Teacher
from scenesplat_stereo.shards.encode import JPEG_ENCODERS, decode_image, encode_jpeg
from scenesplat_stereo.shards.encode_pool import ENCODER_MODES, SampleEncoder, default_encoder_workers
from scenesplat_stereo.shards.nvjpeg import NvJpegEncoder
from scenesplat_stereo.shards.sample import JPEG_QUALITY
from scenesplat_stereo.shards.webdataset import ShardWriter

# Paper appendix B ("Scene splits and counts", "Rendering and valid masks"): training pairs per subset at
# the subsets' native resolutions.
PAPER_TRAIN_PAIRS = {(616, 456): 174_621, (1752, 1168): 149_196}
OWNER = "scenesplat-stereo bench build"  # recorded beside --out: a rerun may replace its own report
FOV_X_DEG = 70.0  # synthetic camera


@dataclass
class Timing:
    """One timed run: counts, wall clock and its split (seconds), megabytes written."""

    pairs: int
    renders: int
    wall_s: float
    render_s: float
    encode_s: float
    write_s: float
    wait_s: float
    mbytes: float

    @property
    def rate(self) -> float:
        """Pairs per second of the whole pipeline."""
        return self.pairs / self.wall_s


@dataclass
class Row:
    """One setting measured several times (``runs``, in order)."""

    label: str
    size: tuple[int, int]
    runs: list[Timing]

    @property
    def median(self) -> Timing:
        return sorted(self.runs, key=lambda t: t.rate)[len(self.runs) // 2]

    def row(self) -> str:
        w, h = self.size
        m, rates = self.median, [t.rate for t in self.runs]
        spread = (max(rates) - min(rates)) / m.rate
        return (f"| {self.label} | {w}x{h} | {m.rate:.3f} | {min(rates):.1f}-{max(rates):.1f} | {100 * spread:.0f}% | "
                f"{m.renders / m.wall_s:.2f} | {1e3 * m.render_s / m.pairs:.1f} | {1e3 * m.encode_s / m.pairs:.1f} | "
                f"{1e3 * m.write_s / m.pairs:.1f} | {1e3 * m.wait_s / m.pairs:.1f} | {m.mbytes / m.pairs:.2f} |")


HEADER = ("| setting | size | pairs/s (median) | min-max | spread | renders/s | render ms/pair | "
          "encode worker-ms/pair | write ms/pair | wait-for-encoder ms/pair | MB/pair |\n"
          "|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")


def synthetic_teacher(n: int, sh_degree: int, frames: int, size: tuple[int, int], device: str) -> tuple[Teacher, dict]:
    """A room of n Gaussians and a Teacher record for its trajectory (no file on disk)."""
    scene = make_room(seed=0, sh_degree=sh_degree, num_gaussians=n)
    c2w = room_trajectory(frames, seed=0)
    w, h = size
    fx = 0.5 * w / math.tan(math.radians(0.5 * FOV_X_DEG))
    K = intrinsics_matrix(fx, fx, 0.5 * w, 0.5 * h)
    teacher = Teacher(scene_id="bench", subset="bench", layout="plain", ply_path=Path("-"), psnr=33.0, c2w=c2w,
                      Ks=np.repeat(K[None], frames, 0), width=w, height=h, sh_degree=sh_degree,
                      camera_convention="opencv", frame_names=[str(i) for i in range(frames)])
    return teacher, scene.to_torch(device)


def _pipeline(plans: list[SamplePlan], render, settings: BuildSettings, folder: Path) -> tuple[float, float, int, object]:
    """Run plans through render -> encode -> write into ``folder``: (wall s, render s, renders, encoder)."""
    now = synced_clock(settings.device)
    t0, render_s, renders = now(), 0.0, 0
    with ShardWriter(folder, "bench", settings.samples_per_shard) as writer:  # shards as the build writes them
        with SampleEncoder(writer.add, settings.workers, settings.jpeg_quality, mode=settings.encoder_mode) as enc:
            batches = [plans[s:s + settings.batch_pairs] for s in range(0, len(plans), settings.batch_pairs)]
            rendered = stream_samples(batches, render)
            for batch in batches:
                t1 = time.perf_counter()
                samples = next(rendered)
                render_s += time.perf_counter() - t1
                renders += sum(2 + len(p.target_ids) for p in batch)
                for s in samples:
                    enc.submit(s)
    return time.perf_counter() - t0, render_s, renders, enc


def time_pipeline(label: str, teacher: Teacher, gaussians: dict, settings: BuildSettings, size: tuple[int, int],
                  pairs: int, repeats: int, rasterize=rasterization) -> Row:
    """Warm the whole pipeline up (kernels, pinned host buffers, the encoder pool and its slots at this
    size: the first run at a new size is otherwise much slower), then time ``pairs`` pairs ``repeats``
    times."""
    plans = plan_scene(teacher, "train", resolution=size)
    plans = (plans * math.ceil(pairs / len(plans)))[:pairs]
    plans = [replace(p, key=f"bench__{i:06d}") for i, p in enumerate(plans)]

    jpeg = NvJpegEncoder(settings.device, settings.jpeg_quality) if settings.jpeg_encoder == "nvjpeg" else None

    def render(batch):
        return start_render(gaussians, teacher.sh_degree, batch, settings.device, settings.with_depth,
                            settings.effects, rasterize, jpeg)

    runs = []
    encoder_closed = contextlib.closing(jpeg) if jpeg is not None else contextlib.nullcontext()
    with tempfile.TemporaryDirectory() as tmp, encoder_closed:
        # As many pairs as a timed run: the pinned host buffers of samples still queued for the encoders
        # are allocated (slowly, cudaHostAlloc) until torch's host cache holds enough of them.
        _pipeline(plans, render, settings, Path(tmp) / "warm-up")
        for r in range(repeats):
            folder = Path(tmp) / f"timed-{r}"
            wall, render_s, renders, enc = _pipeline(plans, render, settings, folder)
            mbytes = sum(f.stat().st_size for f in folder.rglob("*.tar")) / 1e6
            runs.append(Timing(len(plans), renders, wall, render_s, enc.encode_s, enc.sink_s, enc.wait_s, mbytes))
    return Row(label, size, runs)


def encoder_scaling(teacher: Teacher, gaussians: dict, settings: BuildSettings, size: tuple[int, int],
                    pairs: int, repeats: int) -> list[tuple[int, list[float]]]:
    """Encode the same rendered samples with 1, 2, 4, 8, 12, 16 and all-cores workers (up to the CPU
    cores) in ``settings.encoder_mode``, each after one untimed run: (workers, pairs/s of each run)."""
    plans = plan_scene(teacher, "train", resolution=size)[:max(1, pairs)]
    samples = start_render(gaussians, teacher.sh_degree, plans, settings.device).samples()
    out = []
    cores = os.cpu_count() or 1
    for workers in sorted({n for n in (1, 2, 4, 8, 12, 16) if n <= cores} | {cores}):
        rates = []
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            with SampleEncoder(lambda k, m: None, workers, settings.jpeg_quality, mode=settings.encoder_mode) as enc:
                for s in samples:
                    enc.submit(s)
            rates.append(len(samples) / (time.perf_counter() - t0))
        out.append((workers, rates[1:]))
    return out


def jpeg_comparison(teacher: Teacher, gaussians: dict, settings: BuildSettings, size: tuple[int, int],
                    pairs: int, repeats: int) -> str:
    """One table row: the same rendered images (``pairs`` pairs, 12 each) JPEG-encoded by nvJPEG in one
    call (median ms per image over ``repeats`` calls after one untimed) and by the host encoder one at a
    time; mean KB per image and PSNR (dB, decoded against the rendered uint8 pixels) of each."""
    plans = plan_scene(teacher, "train", resolution=size)[:max(1, pairs)]
    samples = start_render(gaussians, teacher.sh_degree, plans, settings.device).samples()
    images = np.stack([im for s in samples for im in (s.left, s.right, *s.targets)])
    device_images = torch.from_numpy(images).to(settings.device)
    times = []
    now = synced_clock(settings.device)
    with contextlib.closing(NvJpegEncoder(settings.device, settings.jpeg_quality)) as enc:
        for _ in range(repeats + 1):
            t0 = now()
            gpu = enc.encode(device_images).result()
            times.append((time.perf_counter() - t0) / len(images))
    t0 = time.perf_counter()
    cpu = [encode_jpeg(im, settings.jpeg_quality) for im in images]
    cpu_ms = 1e3 * (time.perf_counter() - t0) / len(images)

    def psnr(files: list[bytes]) -> float:
        mse = np.mean([np.mean((decode_image(f, "jpg").astype(float) - im) ** 2) for f, im in zip(files, images)])
        return psnr_from_mse(mse, 255.0)

    kb = [sum(map(len, files)) / len(files) / 1e3 for files in (gpu, cpu)]
    return (f"| {size[0]}x{size[1]} | {len(images)} | {1e3 * statistics.median(times[1:]):.3f} | {cpu_ms:.2f} | "
            f"{kb[0]:.1f} | {kb[1]:.1f} | {psnr(gpu):.2f} | {psnr(cpu):.2f} |")


def projection(base: dict[tuple[int, int], Row]) -> list[str]:
    """Projected hours for the paper's training set from the medians of the base rows."""
    lines, total = [], 0.0
    for size, n_pairs in PAPER_TRAIN_PAIRS.items():
        if size in base:
            rate, how = base[size].median.rate, "measured"
        else:
            ref = min(base, key=lambda s: abs(math.log(s[0] * s[1] / (size[0] * size[1]))))
            rate = base[ref].median.rate * (ref[0] * ref[1]) / (size[0] * size[1])
            how = f"scaled by pixel count from {ref[0]}x{ref[1]}"
        hours = n_pairs / rate / 3600
        total += hours
        lines.append(f"| {size[0]}x{size[1]} | {n_pairs:,} | {rate:.3f} ({how}) | {hours:.2f} |")
    lines.append(f"| **total** | {sum(PAPER_TRAIN_PAIRS.values()):,} | | **{total:.2f}** |")
    return ["| size | pairs (x12 images) | pairs/s (median) | hours |", "|---|---:|---|---:|"] + lines


def _sizes(text: str) -> list[tuple[int, int]]:
    return [tuple(int(v) for v in s.lower().split("x")) for s in text.split(",") if s.strip()]


def add_arguments(p) -> None:
    p.add_argument("--gaussians", type=int, default=1_000_000, help="Gaussians in the synthetic room (default 1M)")
    p.add_argument("--sh-degree", type=int, default=3, help="SH degree of the synthetic teacher (default 3)")
    p.add_argument("--sizes", default="616x456,1752x1168", help="WxH render sizes, comma-separated (pixels)")
    p.add_argument("--pairs", type=int, default=32, help="timed pairs per run (12 renders each; default 32)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per row, after one untimed (default 3)")
    p.add_argument("--frames", type=int, default=64, help="trajectory frames the pairs cycle through (default 64)")
    p.add_argument("--batch-pairs", type=int, default=4, help="pairs per rasterisation call (default 4)")
    p.add_argument("--workers", type=int, default=default_encoder_workers(),
                   help="encoder workers (default: half the CPU cores)")
    p.add_argument("--encoder-modes", default="threads,processes",
                   help="encoder modes of the base rows and the scaling table, the first for the other rows "
                   "(default threads,processes)")
    p.add_argument("--jpeg-encoders", default="cpu",
                   help="JPEG encoders of the base rows, from cpu,nvjpeg (nvjpeg: CUDA and nvJPEG; default cpu)")
    p.add_argument("--qualities", default="75,100", help="extra JPEG qualities timed at the first size (default 75,100)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cpu or cuda")
    p.add_argument("--gsplat", action="store_true", help="also time the pipeline rendering with gsplat (if importable)")
    p.add_argument("--out", type=Path, help="also write the markdown to this file (a report of an earlier run of "
                   "this bench is replaced, any other file refused)")


def run(args) -> int:
    sizes = _sizes(args.sizes)
    modes = [m.strip() for m in args.encoder_modes.split(",") if m.strip()]
    jpegs = [m.strip() for m in args.jpeg_encoders.split(",") if m.strip()]
    if (not modes or any(m not in ENCODER_MODES for m in modes) or not jpegs
            or any(j not in JPEG_ENCODERS for j in jpegs) or args.repeats < 1):
        raise ValueError(f"bench build: --encoder-modes from {','.join(ENCODER_MODES)}; --jpeg-encoders from "
                         f"{','.join(JPEG_ENCODERS)}; --repeats >= 1")
    report = OwnedFile(args.out, "--out", OWNER)  # before any work
    if "nvjpeg" in jpegs:
        BuildSettings(teachers=Path("-"), out=Path("-"), device=args.device, jpeg_encoder="nvjpeg")  # refuses early
    settings = BuildSettings(teachers=Path("-"), out=Path("-"), device=args.device, workers=args.workers,
                             batch_pairs=args.batch_pairs, progress=False, encoder_mode=modes[0])
    teacher, gaussians = synthetic_teacher(args.gaussians, args.sh_degree, args.frames, sizes[0], args.device)
    device = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"CPU ({torch.get_num_threads()} threads)"
    out = [f"bench build: {args.gaussians:,} Gaussians, SH {args.sh_degree}, {args.pairs} pairs per run, "
           f"{args.repeats} timed runs per row after one untimed, {args.batch_pairs} pairs per call, "
           f"{args.workers} encoder workers, {os.cpu_count()} CPU cores, device {device}\n"]
    print(out[0], flush=True)
    n, rows = args.pairs, []
    base = {(j, m): {} for j in jpegs for m in modes}

    def timed(label: str, s: BuildSettings, size: tuple[int, int], rasterize=rasterization) -> Row:
        rows.append(time_pipeline(label, teacher, gaussians, s, size, n, args.repeats, rasterize))
        print(rows[-1].row(), flush=True)
        return rows[-1]

    for jpeg, mode in base:
        for size in sizes:
            base[jpeg, mode][size] = timed(f"base (RGB, q92, no effects, no depth), {jpeg} JPEG, {mode}",
                                           replace(settings, encoder_mode=mode, jpeg_encoder=jpeg), size)
    first = sizes[0]
    for q in (int(v) for v in args.qualities.split(",") if v.strip()):
        timed(f"JPEG quality {q}", replace(settings, jpeg_quality=q), first)
    timed("+ left depth (RGB+ED, EXR)", replace(settings, with_depth=True), first)
    timed("+ effects (noise, vignetting, exposure)", replace(settings, effects=CameraEffects.parse(
        "noise,vignetting,exposure")), first)
    if args.gsplat:
        if importlib.util.find_spec("gsplat") is None or not args.device.startswith("cuda"):
            out.append("(--gsplat: gsplat is not importable or the device is not CUDA; skipped)\n")
        else:
            from gsplat import rasterization as gsplat_rasterization

            for size in sizes:
                timed(f"gsplat renderer, base, {modes[0]}", settings, size, gsplat_rasterization)
    out += [HEADER, *(r.row() for r in rows)]
    out.append(f"\nEncoder workers at {first[0]}x{first[1]} (q{JPEG_QUALITY}, same rendered samples, "
               f"{args.repeats} runs after one untimed):\n")
    out.append("| mode | workers | pairs/s encoded (median) | min-max | spread |\n|---|---:|---:|---|---:|")
    for mode in modes:
        for workers, rates in encoder_scaling(teacher, gaussians, replace(settings, encoder_mode=mode), first,
                                              args.pairs, args.repeats):
            med = statistics.median(rates)
            out.append(f"| {mode} | {workers} | {med:.2f} | {min(rates):.1f}-{max(rates):.1f} | "
                       f"{100 * (max(rates) - min(rates)) / med:.0f}% |")
    if "nvjpeg" in jpegs:
        out.append(f"\nJPEG encoders on the same rendered images (q{settings.jpeg_quality}, 4:2:0; nvJPEG: all "
                   f"images in one call, median of {args.repeats} after one untimed; host: one image at a time, "
                   "one thread):\n")
        out.append("| size | images | nvJPEG ms/image | host ms/image | nvJPEG KB | host KB | nvJPEG PSNR dB | "
                   "host PSNR dB |\n|---|---:|---:|---:|---:|---:|---:|---:|")
        out += [jpeg_comparison(teacher, gaussians, settings, size, args.batch_pairs, args.repeats) for size in sizes]
    for jpeg, mode in base:
        out.append(f"\nProjected time of the paper's training set on this device ({device}), {jpeg} JPEG, "
                   f"encoder {mode}, from medians:\n")
        out += projection(base[jpeg, mode])
    doc = "\n".join(out) + "\n"
    print(doc)
    report.write(doc)
    return 0
