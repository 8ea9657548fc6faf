"""``sgmodel predict --video`` on a short stereo clip rendered from a demo teacher (scripts/figures/video_demo.py,
lossless FFV1): the same Gaussians as per-frame ``predict`` and the same rendered frames; side-by-side and
left/right inputs agree; the codecs OpenCV writes here; trajectories; bad input (exit 2, nothing written);
the scene writer processes: the serial bytes, one clean error, nothing left after an error or Ctrl-C, a
process that dies."""

from __future__ import annotations

import math
import os
import re
import time
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from scenesplat_stereo.common import scratch
from scenesplat_stereo.scene.gaussians import load_ply
from scenesplat_stereo.scene.scene_files import FORMATS
from scenesplat_stereo.shards.encode import encode_png, to_uint8
from scripts.figures.video_demo import read_frames, render_clip
from sgmodel.model.render import render_views
from sgmodel.predict import command as predict_mod
from sgmodel.predict import export, video
from sgmodel.predict.export import offset_camera, orbit_camera
from sgmodel.predict.scene_writers import write_scene
from tests.support import scene_writer_faults as faults
from tests.support.model_helpers import predict_status as run
from tests.support.ply_helpers import random_scene

W, H, FRAMES = 96, 64, 6
COMMON = ["--method", "naive-gs", "--encoder", "sgbm", "--resolution", H, "--device", "cpu", "--no-progress"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("clip")
    lefts = render_clip(folder, FRAMES, W, H, num_gaussians=6000)
    assert lefts.shape == (FRAMES, H, W, 3) and lefts.std() > 10  # textured, not blank
    return folder


@pytest.fixture(scope="module")
def video_out(clip, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("video") / "out"
    import contextlib
    import io

    log = io.StringIO()
    with contextlib.redirect_stdout(log):
        rc = run(["--left-video", clip / "left.mkv", "--right-video", clip / "right.mkv", "--calib", clip / "K.txt",
                  "--out", out, "--frames", "--format", "ply", "--codec", "ffv1", "--trajectory", "offset:0.05,0,0",
                  "--batch-size", 4, *COMMON])
    assert rc == 0, log.getvalue()
    return out, log.getvalue()


def test_video_writes_every_frame_and_a_summary(video_out):
    out, log = video_out
    names = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert names == [".written-by", "cameras.json"] + [f"frames/{i:06d}.ply" for i in range(FRAMES)] + [
        "novel_view.mkv", "settings.json"]
    assert f"{W}x{H} per eye, 30 fps, {FRAMES} frames" in log and "| frames | 6 |" in log and "| batches | 2 |" in log
    assert re.search(r"Gaussians \(all frames\) dropped: no valid stereo depth", log)
    assert read_frames(out / "novel_view.mkv").shape == (FRAMES, H, W, 3)


@pytest.mark.parametrize("frame", [0, FRAMES - 1])  # one frame of each batch (4 + 2)
def test_video_frames_equal_per_frame_predict(clip, video_out, tmp_path, frame):
    """The same Gaussians as ``predict`` on that frame's pair, and the frame rendered from them (the video is
    lossless: up to the float rounding of the .ply's log scales, a level of 8 bits at most)."""
    out, _ = video_out
    for side in ("left", "right"):
        (tmp_path / f"{side}.png").write_bytes(encode_png(read_frames(clip / f"{side}.mkv")[frame]))
    single = tmp_path / "single"
    assert run(["--left", tmp_path / "left.png", "--right", tmp_path / "right.png", "--calib", clip / "K.txt",
                "--out", single, *COMMON[:-1]]) == 0
    assert (out / "frames" / f"{frame:06d}.ply").read_bytes() == (single / "scene.ply").read_bytes()
    scene = load_ply(single / "scene.ply").to_torch()
    K = torch.tensor(np.loadtxt(clip / "K.txt", max_rows=1).reshape(3, 3), dtype=torch.float32)
    g = {"means": scene["means"][None], "quats": scene["quats"][None], "scales": scene["scales"][None],
         "opacities": scene["opacities"][None], "sh": torch.nn.functional.pad(scene["colors"], (0, 0, 0, 8))[None]}
    view = torch.tensor(offset_camera(np.array([0.05, 0, 0])), dtype=torch.float32)[None, None]
    rgb = render_views(g, view, K[None, None], W, H)[0]
    expected = to_uint8(rgb[0, 0].permute(1, 2, 0).numpy()).astype(int)
    got = read_frames(out / "novel_view.mkv")[frame].astype(int)
    assert np.abs(got - expected).max() <= 1 and (got != expected).mean() < 0.01


def test_side_by_side_equals_left_and_right_videos(clip, video_out, tmp_path):
    out, _ = video_out
    sbs = tmp_path / "sbs"
    assert run(["--video", clip / "sbs.mkv", "--calib", clip / "K.txt", "--out", sbs, "--frames", "--format", "ply",
                "--codec", "ffv1", "--trajectory", "offset:0.05,0,0", "--max-frames", 3, *COMMON]) == 0
    for i in range(3):
        assert (sbs / "frames" / f"{i:06d}.ply").read_bytes() == (out / "frames" / f"{i:06d}.ply").read_bytes()
    assert not (sbs / "frames" / "000003.ply").exists()
    np.testing.assert_array_equal(read_frames(sbs / "novel_view.mkv"), read_frames(out / "novel_view.mkv")[:3])


def test_forward_splat_video_and_the_default_compressed_ply_frames(clip, tmp_path):
    out = tmp_path / "fs"
    assert run(["--video", clip / "sbs.mkv", "--calib", clip / "K.txt", "--out", out, "--max-frames", 2,
                "--method", "forward-splat", "--encoder", "sgbm", "--device", "cpu", "--no-progress"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [".written-by", "novel_view.mp4"]
    nb = tmp_path / "nb"
    assert run(["--video", clip / "sbs.mkv", "--calib", clip / "K.txt", "--out", nb, "--max-frames", 1, "--frames",
                *COMMON]) == 0
    assert (nb / "frames" / "000000.compressed.ply").is_file()


def test_side_by_side_of_odd_width_is_refused(tmp_path, monkeypatch):
    """OpenCV's encoders round widths to even numbers, so the decoder is stood in for here."""
    class OddCapture:
        def __init__(self, path):
            pass

        def isOpened(self):
            return True

        def read(self):
            return True, np.zeros((16, 33, 3), np.uint8)

        def get(self, prop):
            return 1.0

        def release(self):
            pass

    (tmp_path / "odd.mkv").write_bytes(b"stand-in")
    monkeypatch.setattr(video.cv2, "VideoCapture", OddCapture)
    with pytest.raises(predict_mod.PredictError, match="odd.mkv: a side-by-side video has an even width, got 33"):
        video.StereoSource(str(tmp_path / "odd.mkv"))


@pytest.mark.parametrize("codec", sorted(video.CODECS))
def test_codecs_write_and_read_back(tmp_path, codec):
    frames = (np.random.default_rng(0).random((3, 32, 48, 3)) * 255).astype(np.uint8)
    frames[:] = cv2.GaussianBlur(frames[0], (0, 0), 3)  # smooth: lossy codecs keep it close
    c = video.CODECS[codec]
    sink = video.VideoSink(tmp_path / f"v{c.suffix}", codec, 30.0, 48, 32)
    sink.submit(0, frames, []).result()
    sink.close()
    back = read_frames(tmp_path / f"v{c.suffix}")
    assert back.shape == frames.shape
    err = np.abs(back.astype(int) - frames)
    assert err.max() == 0 if c.lossless else err.mean() < 4


def test_trajectories():
    assert video.parse_trajectory("offset:0.1,-2e-2,.5").offset == (0.1, -0.02, 0.5)
    t = video.parse_trajectory("orbit")
    assert (t.kind, t.radius, t.period) == ("orbit", None, video.ORBIT_PERIOD)
    t = video.parse_trajectory("orbit:0.2,4")
    np.testing.assert_allclose(t.viewmat(30, 30.0, 2.0), orbit_camera(math.pi / 2, 0.2, 2.0), atol=1e-15)  # 1/4 turn
    np.testing.assert_array_equal(video.parse_trajectory("orbit").viewmat(0, 30.0, 2.0),
                                  orbit_camera(0.0, video.ORBIT_RADIUS * 2.0, 2.0))
    c2w = np.linalg.inv(video.parse_trajectory("offset:0.1,0,0").viewmat(5, 30.0, 2.0))
    np.testing.assert_array_equal(c2w[:3, 3], [0.1, 0, 0])
    for bad in ("circle", "offset:1,2", "orbit:-1", "orbit:1,0", "offset:a,b,c"):
        with pytest.raises(predict_mod.PredictError, match="--trajectory"):
            video.parse_trajectory(bad)


@pytest.fixture()
def bad_inputs(clip, tmp_path):
    (tmp_path / "odd.avi").write_bytes(b"")
    writer = cv2.VideoWriter(str(tmp_path / "small.mkv"), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (W // 2, H))
    for _ in range(FRAMES):
        writer.write(np.zeros((H, W // 2, 3), np.uint8))
    writer.release()
    (tmp_path / "mb.txt").write_text(f"cam0=[50 0 24; 0 50 16; 0 0 1]\nbaseline=100\nwidth={W + 2}\nheight={H}\n")
    (tmp_path / "K.txt").write_text((clip / "K.txt").read_text())
    for name in ("left.mkv", "right.mkv", "sbs.mkv"):
        (tmp_path / name).symlink_to(clip / name)
    return tmp_path


@pytest.mark.parametrize("change,message", [
    ({"--video": "missing.mkv", "--left-video": None, "--right-video": None}, "--video .*missing.mkv: file not found"),
    ({"--video": "odd.avi", "--left-video": None, "--right-video": None}, "odd.avi: not a video OpenCV can decode"),
    ({"--right-video": "small.mkv"}, r"is 96x64, 30 fps, 6 frames but --right-video .* is 48x64"),
    ({"--right-video": None}, "--right-video is missing"),
    ({"--left": "left.mkv"}, "give one input"),
    ({"--calib": "mb.txt"}, rf"width={W + 2}, height={H} do not match .*left.mkv \({W}x{H}\)"),
    ({"--trajectory": "spiral"}, "--trajectory 'spiral'"),
    ({"--method": "forward-splat", "--frames": ""}, "--method forward-splat has none"),
    ({"--batch-size": "0"}, "--batch-size and --max-frames must be at least 1"),
])
def test_bad_video_inputs_exit_2_and_write_nothing(bad_inputs, capsys, change, message):
    args = {"--left-video": "left.mkv", "--right-video": "right.mkv", "--calib": "K.txt", "--method": "naive-gs",
            "--encoder": "sgbm", "--out": "out", "--device": "cpu"}
    args.update(change)
    before = sorted(p.name for p in bad_inputs.iterdir())
    plain = ("--method", "--encoder", "--device", "--trajectory", "--batch-size")
    argv = []
    for k, v in args.items():
        if v is not None:
            argv += [k] if v == "" else [k, v if k in plain else bad_inputs / v]
    assert run(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("sgmodel predict: error: ") and len(err.strip().splitlines()) == 1, err
    assert re.search(message, err), err
    assert sorted(p.name for p in bad_inputs.iterdir()) == before


def test_a_raw_rigs_video_is_rectified_frame_by_frame_like_a_pair(raw_rig, tmp_path):
    """--rig on a video: every frame takes the pair transform of a still pair (rectification, then the resize),
    and the frame's scene is in the raw left camera's frame: byte-identical to `predict --rig` on that pair."""
    from scripts.inputs.rig_pair import H as RH
    from scripts.inputs.rig_pair import W as RW

    r = raw_rig("radtan")
    for side in ("left", "right"):
        image = cv2.imread(str(r.folder / f"{side}.png"), cv2.IMREAD_COLOR)
        writer = cv2.VideoWriter(str(tmp_path / f"{side}.mkv"), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (RW, RH))
        for _ in range(2):
            writer.write(image)
        writer.release()
    common = ["--rig", r.folder / "opencv.yml", "--method", "naive-gs", "--encoder", "sgbm", "--resolution", RH,
              "--device", "cpu"]
    assert run(["--left-video", tmp_path / "left.mkv", "--right-video", tmp_path / "right.mkv", "--out", tmp_path / "v",
                "--frames", "--format", "ply", "--no-progress", *common]) == 0
    assert run(["--left", r.folder / "left.png", "--right", r.folder / "right.png", "--out", tmp_path / "p",
                *common]) == 0
    scene = (tmp_path / "p" / "scene.ply").read_bytes()
    assert (tmp_path / "v" / "frames" / "000000.ply").read_bytes() == scene
    assert (tmp_path / "v" / "frames" / "000001.ply").read_bytes() == scene
    assert (tmp_path / "v" / "settings.json").read_text() == (tmp_path / "p" / "settings.json").read_text()


# ---------------------------------------------------------------- scene writers beside the model

@pytest.mark.parametrize("fmt,quantise_on", [(f, None) for f in sorted(FORMATS)] + [("sog", "cpu")])
def test_scene_writer_processes_write_the_serial_files(tmp_path, fmt, quantise_on):
    """Several scene writer processes at once (and the quantisation's row tasks) write each frame's scene byte for
    byte as ``scene_writers.write_scene`` writes it alone in this process, named by frame number, whatever order
    they finish in; their slots are removed at the end. ``quantise_on``: a SOG quantised in the copying threads
    (``scene_writers.QUANTISED_ON_DEVICE``, as with the model on a GPU; here on the CPU) and encoded in the
    processes."""
    rng = np.random.default_rng(7)
    scenes = [random_scene(rng, 3000 + 4099 * i, i % 3) for i in range(7)]
    folder = tmp_path / "frames"
    folder.mkdir()
    slots_before = set(os.listdir(scratch.scratch_dir()))
    sink = video.VideoSink(tmp_path / "v.mkv", "ffv1", 30.0, 16, 16, folder, fmt, scene_writers=3)
    sink.quantise_on = None if quantise_on is None else torch.device(quantise_on)
    futures = [sink.submit(first, np.zeros((n, 16, 16, 3), np.uint8), lambda i, first=first: scenes[first + i])
               for first, n in ((0, 3), (3, 1), (4, 3))]
    assert all(f.result() > 0 for f in futures)
    sink.close()
    suffix = FORMATS[fmt].suffix
    assert sorted(p.name for p in folder.iterdir()) == [f"{i:06d}{suffix}" for i in range(7)]
    assert sink.processes.busy_s > 0
    assert set(os.listdir(scratch.scratch_dir())) <= slots_before  # the writers' slots are gone
    for i, scene in enumerate(scenes):
        serial = write_scene(scene, tmp_path / f"serial{suffix}", fmt)
        assert (folder / f"{i:06d}{suffix}").read_bytes() == serial.read_bytes(), i


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="needs CUDA (the copying threads' streams, page-locked copies and the SOG quantised there)")
@pytest.mark.parametrize("fmt", ["sog", "ply"])
def test_scenes_copied_on_the_threads_streams_are_the_serial_files(tmp_path, fmt):
    """With the model on a GPU: each copying thread's stream waits for its batch (the Gaussians below are made by
    kernels queued just before ``submit``, with later batches' kernels queued behind them), copies through page-locked
    memory and (SOG) quantises there; every file equals ``write_scene`` of ``to_scene`` in this thread (the SOG
    quantised on the same GPU)."""
    dev = torch.device("cuda")
    folder = tmp_path / "frames"
    folder.mkdir()
    sink = video.VideoSink(tmp_path / "v.mkv", "ffv1", 30.0, 16, 16, folder, fmt, scene_writers=3, device=dev)
    batches, futures = [], []
    for first in (0, 3, 6):
        g = torch.Generator(device=dev).manual_seed(first)
        n = 20_000 + 999 * first
        base = torch.randn(3, n, 3 + 4 + 3 + 1 + 27, device=dev, generator=g)
        big = torch.randn(4096, 4096, device=dev)
        for _ in range(20):  # the model's stream busy well past submit
            big = big @ big / 64.0
        gaussians = {"means": base[..., :3] * 3, "quats": base[..., 3:7], "scales": base[..., 7:10].exp() * 0.05,
                     "opacities": base[..., 10].sigmoid(), "sh": base[..., 11:].reshape(3, n, 9, 3) * 0.3}
        batches.append(gaussians)
        futures.append(sink.submit(first, np.zeros((3, 16, 16, 3), np.uint8),
                                   lambda i, g=gaussians: export.to_scene(g, i)))
    assert all(f.result() > 0 for f in futures)
    sink.close()
    suffix = FORMATS[fmt].suffix
    for b, gaussians in enumerate(batches):
        for i in range(3):
            serial = write_scene(export.to_scene(gaussians, i), tmp_path / f"serial{suffix}", fmt)
            assert (folder / f"{3 * b + i:06d}{suffix}").read_bytes() == serial.read_bytes(), (b, i)


def test_the_streams_cpu_threads(clip, tmp_path, monkeypatch):
    """On a GPU a stream runs with ``GPU_STREAM_CPU_THREADS`` torch threads, except while SOG scenes are quantised in
    this process; on the CPU as they are. The count in force during a stream (here 1, as a GPU stream would set it)
    is set back when the stream ends, after an error too."""
    folder = tmp_path / "frames"
    folder.mkdir()
    gpu = torch.device("cuda")  # (nothing runs there: only the rule is read)
    rule = {(None, "spz"): video.GPU_STREAM_CPU_THREADS, (folder, "compressed-ply"): video.GPU_STREAM_CPU_THREADS,
            (folder, "sog"): None}
    for (scene_folder, fmt), threads in rule.items():
        sink = video.VideoSink(tmp_path / "v.mkv", "ffv1", 30.0, 16, 16, scene_folder, fmt, scene_writers=2, device=gpu)
        sink.close()
        assert sink.cpu_threads == threads, (scene_folder, fmt)
    sink = video.VideoSink(tmp_path / "v.mkv", "ffv1", 30.0, 16, 16, device=torch.device("cpu"))
    sink.close()
    assert sink.cpu_threads is None

    class OneThread(video.VideoSink):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.cpu_threads = 1

        def submit(self, *args):
            seen.append(torch.get_num_threads())
            if len(seen) == 2:
                raise RuntimeError("the second batch fails")
            return super().submit(*args)

    seen, original = [], torch.get_num_threads()
    monkeypatch.setattr(video, "VideoSink", OneThread)
    argv = ["--video", clip / "sbs.mkv", "--calib", clip / "K.txt", "--batch-size", 2, *COMMON]
    torch.set_num_threads(2)
    try:
        assert run([*argv, "--out", tmp_path / "out"]) == 1
        assert seen == [1, 1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(original)


def _scene_frames_argv(clip: Path, out: Path) -> list:
    return ["--video", clip / "sbs.mkv", "--calib", clip / "K.txt", "--out", out, "--frames", "--format", "spz",
            "--batch-size", 2, *COMMON]


@pytest.mark.parametrize("write,status", [(faults.value_error_write, 2), (faults.runtime_error_write, 1)])
def test_a_scene_writers_error_ends_predict_once_and_writes_nothing(clip, tmp_path, monkeypatch, capsys, write,
                                                                    status):
    """An error in a scene writer process (bad input: ValueError or OSError, exit 2; anything else a bug,
    exit 1) ends the command with its one line, and OUT is not written."""
    monkeypatch.setattr(video, "write_scene", write)
    assert run(_scene_frames_argv(clip, tmp_path / "out")) == status
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]  # (not the warnings)
    assert len(errors) == 1 and errors[0].startswith("sgmodel predict: error: "), errors
    assert f"{faults.FAILING_FRAME}.spz: broken on purpose" in errors[0]
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_while_scenes_are_written_leaves_no_file(clip, tmp_path, monkeypatch):
    """Ctrl-C in the main thread while scene writer processes are writing: exit 130 once the started writes end,
    and neither OUT nor a staging folder or temp file remains."""
    submit = video.VideoSink.submit

    def interrupt_second(self, first, *rest):
        if first > 0:
            deadline = time.monotonic() + 30
            while not list(tmp_path.rglob(faults.STARTED)):
                assert time.monotonic() < deadline, "no write started"
                time.sleep(0.01)
            raise KeyboardInterrupt
        return submit(self, first, *rest)

    monkeypatch.setattr(video, "write_scene", faults.slow_write)
    monkeypatch.setattr(video.VideoSink, "submit", interrupt_second)
    assert run(_scene_frames_argv(clip, tmp_path / "out")) == 130
    assert list(tmp_path.iterdir()) == []


def test_a_scene_the_quantisation_refuses_ends_the_stream_naming_the_file(tmp_path):
    """A scene the format cannot hold, found by the quantisation in a copying thread (a SOG of no Gaussians): the
    batch's future raises the writer's ValueError naming the frame's file (exit 2), and nothing is written."""
    folder = tmp_path / "frames"
    folder.mkdir()
    sink = video.VideoSink(tmp_path / "v.mkv", "ffv1", 30.0, 16, 16, folder, "sog", scene_writers=2)
    sink.quantise_on = torch.device("cpu")
    try:
        empty = random_scene(np.random.default_rng(0), 0, 0)
        with pytest.raises(ValueError, match=r"000000\.sog: an empty scene has no SOG"):
            sink.submit(0, np.zeros((1, 16, 16, 3), np.uint8), lambda i: empty).result(timeout=60)
    finally:
        sink.close(cancel=True)
    assert list(folder.iterdir()) == []


def test_a_writer_process_that_dies_ends_the_stream(tmp_path):
    """A writer process killed mid-stream (out of memory, say): the batch's future raises BrokenProcessPool (a
    RuntimeError: exit 1 on the command line) instead of waiting for ever."""
    folder = tmp_path / "frames"
    folder.mkdir()
    sink = video.VideoSink(tmp_path / "v.mkv", "ffv1", 30.0, 16, 16, folder, "spz", scene_writers=2)
    try:
        for writer in sink.processes.writers:
            writer.process.kill()
        scene = random_scene(np.random.default_rng(0), 100, 0)
        with pytest.raises(BrokenProcessPool):
            sink.submit(0, np.zeros((1, 16, 16, 3), np.uint8), lambda i: scene).result(timeout=60)
    finally:
        sink.close(cancel=True)
