"""``scenesplat-stereo bench encode``: where the build's host encoding time goes, without a GPU.

Synthetic samples as the build renders them (left, right, ``--targets`` targets as uint8 RGB, their
bool masks; smooth shading, texture and noise, so JPEG sizes are near those of rendered rooms) at each
``--sizes`` entry. Two tables, each row measured ``--repeats`` times after one untimed run, reported as
min / median / max and the spread (max - min) / median:

1. One image, one call at a time (ms per image): the JPEG (quality 92, 4:2:0), the mask PNG and the depth
   EXR through ``encode.py``; of that, the scratch-file round trip of the OpenImageIO-written files (the
   encoded bytes written to, read back from and removed from the scratch folder, timed alone; masks are
   encoded in memory); and the JPEG again beside a pure-Python
   thread (what waiting for the GIL does to each call).
2. Samples per second of the whole ``SampleEncoder`` (bounded queue, in-order writer thread, tar shards
   written by ``ShardWriter`` into a temporary folder) for each ``--modes`` entry and ``--workers`` count,
   ``--samples`` samples per run. ``threads-oiio1``: threads with OpenImageIO's own ``threads`` attribute
   set to 1 for the run. "worker-ms/sample" is ``encode_s`` per sample: above the one-call cost x images
   per sample, the excess is contention (cores, GIL, copies).
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from scenesplat_stereo.build.protocol import NUM_TARGETS
from scenesplat_stereo.common import scratch
from scenesplat_stereo.common.commandline import Parser, run_command
from scenesplat_stereo.common.ownership import OwnedFile
from scenesplat_stereo.common.text import parse_size
from scenesplat_stereo.shards import encode
from scenesplat_stereo.shards.encode import SampleImages
from scenesplat_stereo.shards.encode_pool import SampleEncoder
from scenesplat_stereo.shards.webdataset import ShardWriter

BENCH_MODES = ("threads", "processes", "threads-oiio1")
OWNER = "scenesplat-stereo bench encode"  # recorded beside --out: a rerun may replace its own report


def synthetic_image(w: int, h: int, seed: int) -> np.ndarray:
    """[h, w, 3] uint8: smooth shading, 4-pixel texture blocks and fine noise (JPEG sizes of rendered rooms)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    base = np.stack([0.5 + 0.3 * np.sin(x / (37 + 7 * c) + y / (53 + 5 * c) + seed + c) for c in range(3)], -1)
    texture = rng.normal(0, 0.04, (h // 4 + 1, w // 4 + 1, 3)).astype(np.float32).repeat(4, 0).repeat(4, 1)[:h, :w]
    return encode.to_uint8(np.clip(base + texture + rng.normal(0, 0.01, (h, w, 3)).astype(np.float32), 0, 1))


def synthetic_sample(w: int, h: int, seed: int, targets: int = NUM_TARGETS) -> SampleImages:
    """One sample of ``targets`` targets: images from ``synthetic_image``, masks of a few rectangles."""
    imgs = [synthetic_image(w, h, seed * 16 + i) for i in range(2 + targets)]
    masks = np.ones((targets, h, w), bool)
    for t in range(targets):
        masks[t, : h // (3 + t), : w // 5] = False
        masks[t, h // 2:, w - w // (4 + t):] = False
    return SampleImages(key=f"bench__{seed:06d}", left=imgs[0], right=imgs[1], targets=np.stack(imgs[2:]),
                        masks=masks, target_ids=tuple(range(targets)), meta=json.dumps(
                            {"scene": "bench", "subset": "bench", "teacher_psnr": 33.0, "targets": [None] * targets}).encode())


def stats(values: list[float]) -> tuple[float, float, float, float]:
    """(min, median, max, spread = (max - min) / median) of ``values``."""
    med = statistics.median(values)
    return min(values), med, max(values), (max(values) - min(values)) / med if med else float("nan")


def fmt(values: list[float], digits: int = 2) -> str:
    lo, med, hi, spread = stats(values)
    return f"{med:.{digits}f} | {lo:.{digits}f}-{hi:.{digits}f} | {100 * spread:.0f}%"


def _per_call_ms(fn: Callable[[], object], calls: int) -> float:
    t0 = time.perf_counter()
    for _ in range(calls):
        fn()
    return 1e3 * (time.perf_counter() - t0) / calls


def _round_trip(data: bytes, ext: str) -> None:
    path = encode._scratch_path(ext)
    with open(path, "wb") as f:
        f.write(data)
    with open(path, "rb") as f:
        f.read()
    os.remove(path)


def _beside_busy_thread(fn: Callable[[], object], calls: int) -> float:
    """ms per call of ``fn`` while another thread runs pure Python (holding the GIL between switches)."""
    stop = threading.Event()

    def spin() -> None:
        n = 0
        while not stop.is_set():
            n += 1

    t = threading.Thread(target=spin, daemon=True)
    t.start()
    try:
        return _per_call_ms(fn, calls)
    finally:
        stop.set()
        t.join()


def image_table(sizes: list[tuple[int, int]], repeats: int, calls: int) -> list[str]:
    """Table 1 (see the module docstring)."""
    lines = ["| size | image | KB | ms per call: median | min-max | spread | of which scratch round trip, ms |",
             "|---|---|---:|---:|---|---:|---:|"]
    for w, h in sizes:
        s = synthetic_sample(w, h, 0, targets=1)
        depth = np.linspace(0.5, 8.0, w * h, dtype=np.float32).reshape(h, w)
        cases = [("JPEG q92", "jpg", lambda: encode.encode_jpeg(s.left)),
                 ("mask PNG (zlib, in memory)", None, lambda: encode.encode_mask_png(s.masks[0])),
                 ("depth EXR", "exr", lambda: encode.encode_depth_exr(depth))]
        for name, ext, fn in cases:
            data = fn()
            times = [_per_call_ms(fn, calls) for _ in range(repeats)]
            trips = [] if ext is None else [_per_call_ms(lambda: _round_trip(data, ext), calls) for _ in range(repeats)]
            trip = f"{statistics.median(trips):.3f}" if trips else ""  # masks: encoded in memory, no round trip
            lines.append(f"| {w}x{h} | {name} | {len(data) / 1e3:.0f} | {fmt(times)} | {trip} |")
        busy = [_beside_busy_thread(cases[0][2], calls) for _ in range(repeats)]
        lines.append(f"| {w}x{h} | JPEG q92 beside a busy Python thread | | {fmt(busy)} | |")
    return lines


def time_encoder(samples: list[SampleImages], mode: str, workers: int, folder: Path) -> tuple[float, float]:
    """One run of ``samples`` through a ``SampleEncoder`` into tar shards in ``folder``:
    (samples/s, encoder worker-ms per sample)."""
    old = oiio.get_int_attribute("threads")
    if mode == "threads-oiio1":
        oiio.attribute("threads", 1)
    try:
        t0 = time.perf_counter()
        with ShardWriter(folder, "bench", len(samples)) as writer:
            with SampleEncoder(writer.add, workers, mode=mode.removesuffix("-oiio1")) as enc:
                for s in samples:
                    enc.submit(s)
        wall = time.perf_counter() - t0
    finally:
        oiio.attribute("threads", old)
    return len(samples) / wall, 1e3 * enc.encode_s / len(samples)


def encoder_table(sizes: list[tuple[int, int]], modes: list[str], workers: list[int], repeats: int,
                  n_samples: int, targets: int) -> list[str]:
    """Table 2 (see the module docstring)."""
    lines = ["| size | mode | workers | samples/s: median | min-max | spread | worker-ms/sample (median) |",
             "|---|---|---:|---:|---|---:|---:|"]
    for w, h in sizes:
        distinct = [synthetic_sample(w, h, i, targets) for i in range(min(n_samples, 8))]
        samples = [replace(distinct[i % len(distinct)], key=f"bench__{i:06d}") for i in range(n_samples)]
        for mode in modes:
            for n in workers:
                with tempfile.TemporaryDirectory(prefix="bench-encode-") as tmp:
                    runs = [time_encoder(samples, mode, n, Path(tmp) / str(r)) for r in range(repeats + 1)][1:]
                rates = [r for r, _ in runs]
                per = statistics.median(m for _, m in runs)
                lines.append(f"| {w}x{h} | {mode} | {n} | {fmt(rates)} | {per:.1f} |")
                print(lines[-1], flush=True)
    return lines


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def add_arguments(p) -> None:
    p.add_argument("--sizes", default="616x456,1752x1168", help="WxH image sizes, comma-separated (pixels)")
    p.add_argument("--workers", default=f"1,2,{max(2, (os.cpu_count() or 1) // 2)},{os.cpu_count() or 1}",
                   help="encoder worker counts, comma-separated (default: 1, 2, half and all the CPU cores)")
    p.add_argument("--modes", default=",".join(BENCH_MODES), help=f"from {','.join(BENCH_MODES)}")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per row, after one untimed (default 5)")
    p.add_argument("--samples", type=int, default=24, help="samples (pairs) per encoder run (default 24)")
    p.add_argument("--targets", type=int, default=NUM_TARGETS, help=f"targets per sample (default {NUM_TARGETS})")
    p.add_argument("--calls", type=int, default=20, help="calls per one-image timing (default 20)")
    p.add_argument("--out", type=Path, help="also write the markdown to this file (a report of an earlier run of "
                   "this bench is replaced, any other file refused)")


def run(args) -> int:
    sizes = [parse_size(s) for s in args.sizes.split(",") if s.strip()]
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    workers = _ints(args.workers)
    bad = [m for m in modes if m not in BENCH_MODES]
    if bad or args.repeats < 1 or args.samples < 1 or not workers or min(workers) < 1:
        raise ValueError(f"bench encode: bad --modes {bad} or --repeats/--samples/--workers below 1")
    out = OwnedFile(args.out, "--out", OWNER)  # before any work
    head = (f"bench encode: OpenImageIO {oiio.__version__} (threads attribute {oiio.get_int_attribute('threads')}), "
            f"{os.cpu_count()} CPU cores, scratch folder {scratch.scratch_dir()}, {args.repeats} timed runs per row "
            f"after one untimed; samples of 2 + {args.targets} images and {args.targets} masks\n")
    print(head, flush=True)
    t1 = image_table(sizes, args.repeats, args.calls)
    print("\n".join(t1) + "\n", flush=True)
    t2 = encoder_table(sizes, modes, workers, args.repeats, args.samples, args.targets)
    doc = "\n".join([head, "One image, one call at a time:\n", *t1, "",
                     f"Whole SampleEncoder into tar shards, {args.samples} samples per run:\n", *t2, ""])
    out.write(doc)
    return 0


if __name__ == "__main__":
    import argparse

    parser = Parser(prog="bench encode", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    parser.set_defaults(func=run)
    raise SystemExit(run_command(parser))  # errors as the command's: one line, exit 2 for a refused --out
