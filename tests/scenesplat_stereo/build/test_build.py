"""build.py end to end on tiny teachers: shards per SPEC, masks against rendered alpha, resume after a kill,
malformed teachers, byte-identical rebuilds, Ray, the real guitar teacher."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import tarfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from scenesplat_stereo.build import run as build_mod
from scenesplat_stereo.build.effects import CameraEffects
from scenesplat_stereo.build.run import BuildSettings, build, summary
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.scene.cameras import viewmats_from_c2w
from scenesplat_stereo.scene.gaussians import GaussianScene, load_ply, save_ply
from scenesplat_stereo.scene.teachers import OrbitSpec
from scenesplat_stereo.shards import webdataset as shards
from scenesplat_stereo.shards.encode import decode_image
from tests.support.paths import REPO

SIZE = (32, 24)


def write_teacher(folder: Path, seed: int = 0, n: int = 300, frames: int = 5, psnr: float | None = 33.0,
                  subset: str = "ScanNetGS", sh_degree: int = 0, size: tuple[int, int] = SIZE,
                  trajectory: bool = True) -> Path:
    """A plain-layout teacher: n random Gaussians 2.5-4 m in front of a camera that steps 0.1 m along x
    per frame (OpenCV transforms.json), scene.json with the PSNR and subset."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    means = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2.5, 4, n)]
    q = rng.normal(size=(n, 4))
    sh = rng.normal(0, 0.3, (n, (sh_degree + 1) ** 2, 3))
    sh[:, 1:] *= 0.1
    scene = GaussianScene(means.astype(np.float32), (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                          rng.uniform(0.05, 0.25, (n, 3)).astype(np.float32), rng.uniform(0.5, 1.0, n).astype(np.float32),
                          sh.astype(np.float32), sh_degree)
    save_ply(scene, folder / "point_cloud.ply")
    w, h = size
    if trajectory:
        poses = [np.eye(4) for _ in range(frames)]
        for f, c2w in enumerate(poses):
            c2w[0, 3] = 0.1 * f
        (folder / "transforms.json").write_text(json.dumps({
            "camera_convention": "opencv", "fl_x": 0.8 * w, "fl_y": 0.8 * w, "cx": w / 2, "cy": h / 2, "w": w, "h": h,
            "frames": [{"file_path": f"{i}.jpg", "transform_matrix": m.tolist()} for i, m in enumerate(poses)]}))
    meta = {"subset": subset, "camera_convention": "opencv"} | ({"psnr": psnr} if psnr is not None else {})
    (folder / "scene.json").write_text(json.dumps(meta))
    return folder


def write_teachers(root: Path, frames: int = 5) -> Path:
    """Three teachers, one per PSNR tier and SH degrees 0, 1, 3."""
    for i, (psnr, deg) in enumerate([(33.0, 0), (37.0, 1), (41.0, 3)]):
        write_teacher(root / f"room{i}", seed=i, psnr=psnr, sh_degree=deg, frames=frames)
    return root


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def settings(teachers: Path, out: Path, **kw) -> BuildSettings:
    base = dict(val_scenes=1, samples_per_shard=2, workers=2, batch_pairs=2, progress=False)
    return BuildSettings(teachers=teachers, out=out, **(base | kw))


@pytest.fixture(scope="module")
def teachers(tmp_path_factory) -> Path:
    return write_teachers(tmp_path_factory.mktemp("teachers"))


@pytest.fixture(scope="module")
def built(teachers, tmp_path_factory) -> tuple[Path, build_mod.BuildReport]:
    out = tmp_path_factory.mktemp("out")
    return out, build(settings(teachers, out))


def samples(out: Path, split: str) -> list[tuple[str, dict[str, bytes]]]:
    """The samples of a split, read with plain ``tarfile`` and WebDataset's grouping (key = member name up
    to the first '.', consecutive members of a key form a sample), shards in index.json order."""
    index = json.loads((out / split / "index.json").read_text())
    groups: list[tuple[str, dict[str, bytes]]] = []
    for entry in index["shards"]:
        with tarfile.open(out / split / entry["name"]) as tar:
            for m in tar:
                key, suffix = m.name.split(".", 1)
                if not groups or groups[-1][0] != key:
                    groups.append((key, {}))
                groups[-1][1][suffix] = tar.extractfile(m).read()
    assert [k for k, _ in groups] == [k for e in index["shards"] for k in e["keys"]]
    return groups


def test_layout_counts_and_members(built):
    out, report = built
    assert not report.failed
    # val_scenes=1 of 3 scenes (seed 42 split); train scenes: every frame, 10 targets; val: 5 frames, 4 targets
    train, val = samples(out, "train"), samples(out, "val")
    assert len(train) == 10 and len(val) == 5
    for split, group, ntargets in (("train", train, 10), ("val", val, 4)):
        for key, members in group:
            meta = json.loads(members["json"])
            assert key == f"{meta['scene']}__{meta['frame']:06d}"
            want = {"json", "left.jpg", "right.jpg"} | {f"target_{j:02d}.jpg" for j in range(ntargets)} \
                | {f"mask_{j:02d}.png" for j in range(ntargets)}
            assert set(members) == want, split
            assert (meta["width"], meta["height"]) == SIZE
    stats = json.loads((out / "stats.json").read_text())
    assert stats["total"]["train"] == {"scenes": 2, "pairs": 10, "targets": 100}
    assert stats["total"]["val"] == {"scenes": 1, "pairs": 5, "targets": 20}
    assert stats["teachers"]["trainval"]["found"] == 3 and stats["teachers"]["trainval"]["kept"] == 3
    # shards per teacher: 5 samples at 2 per shard -> 3 shards each, numbered in scene order
    index = json.loads((out / "train/index.json").read_text())
    assert [s["num_samples"] for s in index["shards"]] == [2, 2, 1, 2, 2, 1]
    assert "teachers:" in summary(report)


def test_masks_and_images_match_the_rasteriser(built, teachers):
    out, _ = built
    key, members = samples(out, "train")[3]
    meta = json.loads(members["json"])
    scene = load_ply(teachers / meta["scene"] / "point_cloud.ply")
    c2w = np.concatenate([[meta["c2w_left"], meta["c2w_right"]], meta["targets"]])
    K = torch.tensor(meta["K"], dtype=torch.float32)
    colors, alphas, _ = rasterization(**scene.to_torch(), viewmats=torch.from_numpy(viewmats_from_c2w(c2w)).float(),
                                      Ks=K.expand(len(c2w), 3, 3).contiguous(), width=meta["width"], height=meta["height"],
                                      sh_degree=scene.sh_degree, rasterize_mode="antialiased")
    for i, j in enumerate(meta["target_ids"]):
        mask = decode_image(members[f"mask_{j:02d}.png"], "png")[..., 0]
        assert np.array_equal(mask == 255, alphas[2 + i, ..., 0].numpy() >= 0.5), j
    rgb8 = (colors.clamp(0, 1) * 255).round().numpy()
    for i, name in enumerate(["left.jpg", "right.jpg"] + [f"target_{j:02d}.jpg" for j in meta["target_ids"]]):
        img = decode_image(members[name], "jpg").astype(float)
        assert np.abs(img - rgb8[i]).mean() < 4.0, name  # JPEG q92 on a 32x24 image
    assert not np.array_equal(decode_image(members["left.jpg"], "jpg"), decode_image(members["right.jpg"], "jpg"))
    # the stereo geometry stored: right = T_L Trans(B, 0, 0), tier of 33 dB -> B = 0.05 m
    if meta["teacher_psnr"] == 33.0:
        assert np.allclose(np.array(meta["c2w_right"])[:3, 3] - np.array(meta["c2w_left"])[:3, 3], [0.05, 0, 0])


def test_rebuild_is_byte_identical(built, teachers, tmp_path):
    out, _ = built
    # encoder processes, 1 worker, other batches: the same bytes as the fixture's 2 encoder threads
    report = build(settings(teachers, tmp_path / "again", workers=1, batch_pairs=3, encoder_mode="processes"))
    assert not report.failed
    assert tree(tmp_path / "again") == tree(out)
    # a rerun in place keeps every shard and writes nothing
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "again").rglob("*.tar")}
    again = build(settings(teachers, tmp_path / "again"))
    assert again.skipped_shards == 9 and not again.results
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "again").rglob("*.tar")} == before


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_build_is_byte_identical_and_close_to_cpu(built, teachers, tmp_path):
    out, _ = built
    build(settings(teachers, tmp_path / "cuda1", device="cuda"))
    build(settings(teachers, tmp_path / "cuda2", device="cuda", batch_pairs=3))
    assert tree(tmp_path / "cuda1") == tree(tmp_path / "cuda2")
    for (k0, m0), (k1, m1) in zip(samples(out, "train"), samples(tmp_path / "cuda1", "train")):
        assert k0 == k1 and m0["json"] == m1["json"]
        a, b = decode_image(m0["left.jpg"], "jpg").astype(int), decode_image(m1["left.jpg"], "jpg").astype(int)
        assert np.abs(a - b).max() <= 2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_nvjpeg_build_is_byte_identical_and_close_to_cpu(built, teachers, tmp_path):
    """JPEGs encoded on the GPU: a rebuild (other batches, encoder processes) gives the same bytes; masks
    and JSON are those of the CPU build, the JPEGs decode to nearly the same pixels; OUT records the
    encoder, and resuming it with the CPU encoder is refused."""
    out, _ = built
    for folder, kw in (("nv1", {}), ("nv2", dict(batch_pairs=3, encoder_mode="processes"))):
        report = build(settings(teachers, tmp_path / folder, device="cuda", jpeg_encoder="nvjpeg", **kw))
        assert not report.failed, report.failed[0].error
    assert tree(tmp_path / "nv1") == tree(tmp_path / "nv2")
    cpu, gpu = samples(out, "train"), samples(tmp_path / "nv1", "train")
    assert [k for k, _ in cpu] == [k for k, _ in gpu]
    for (_, m0), (_, m1) in zip(cpu, gpu):
        assert set(m0) == set(m1) and m0["json"] == m1["json"]
        for name in m0:
            if name.endswith(".png"):
                assert m0[name] == m1[name], name
            elif name.endswith(".jpg"):
                a, b = decode_image(m0[name], "jpg").astype(float), decode_image(m1[name], "jpg").astype(float)
                assert np.abs(a - b).mean() < 1.5, name
    assert json.loads((tmp_path / "nv1/build.json").read_text())["trainval"]["jpeg_encoder"] == "nvjpeg"
    with pytest.raises(ValueError, match="jpeg_encoder"):
        build(settings(teachers, tmp_path / "nv1", device="cuda"))


def test_resume_after_an_interrupted_build_gives_the_same_bytes(built, teachers, tmp_path, monkeypatch):
    out, _ = built
    real_add = shards.ShardWriter.add
    calls = {"n": 0}

    def add_then_die(self, key, members):
        real_add(self, key, members)
        calls["n"] += 1
        if calls["n"] == 3:  # one full shard of the first teacher and one sample into its second
            raise KeyboardInterrupt

    monkeypatch.setattr(shards.ShardWriter, "add", add_then_die)
    with pytest.raises(KeyboardInterrupt):
        build(settings(teachers, tmp_path / "resumed"))
    monkeypatch.setattr(shards.ShardWriter, "add", real_add)
    train = tmp_path / "resumed/train"
    assert sorted(p.name for p in train.glob("shard-*.tar")) == ["shard-000000.tar"]
    assert list(train.glob(".tmp-*"))  # the interrupted shard's temp file, as a kill leaves it
    report = build(settings(teachers, tmp_path / "resumed"))
    assert report.skipped_shards == 1
    assert not list(train.glob(".tmp-*"))
    assert tree(tmp_path / "resumed") == tree(out)


@pytest.mark.slow
def test_resume_after_sigkill_of_a_cli_build(tmp_path):
    teachers = tmp_path / "teachers"
    write_teacher(teachers / "big", frames=30, n=1500)
    args = ["build", "--teachers", str(teachers), "--out", str(tmp_path / "killed"), "--samples-per-shard", "2",
            "--batch-pairs", "1", "--workers", "1", "--val-scenes", "0", "--no-progress"]
    proc = subprocess.Popen([sys.executable, "-m", "scenesplat_stereo.cli", *args], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    done_dir = tmp_path / "killed/train/.done"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None and not (done_dir.is_dir() and len(list(done_dir.iterdir())) >= 2):
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = len(list(done_dir.glob("*.json"))) if done_dir.is_dir() else 0
    assert 0 < finished < 15, f"the build was killed after {finished} of 15 shards; the test needs it midway"
    resumed = build(replace(settings(teachers, tmp_path / "killed", val_scenes=0), workers=1, batch_pairs=1))
    assert resumed.skipped_shards >= finished - 1
    build(settings(teachers, tmp_path / "clean", val_scenes=0))
    assert not resumed.failed and tree(tmp_path / "killed") == tree(tmp_path / "clean")


def test_malformed_teachers_are_reported_and_leave_nothing(teachers, tmp_path):
    root = tmp_path / "teachers"
    for i in range(3):
        write_teacher(root / f"good{i}", seed=i)
    nan = write_teacher(root / "nan_means", seed=5)
    data = bytearray((nan / "point_cloud.ply").read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start:start + 4] = struct.pack("<f", float("nan"))  # x of the first Gaussian
    (nan / "point_cloud.ply").write_bytes(bytes(data))
    cut = write_teacher(root / "truncated", seed=6)
    (cut / "point_cloud.ply").write_bytes((cut / "point_cloud.ply").read_bytes()[:3000])
    write_teacher(root / "garbage", seed=7)
    (root / "garbage/point_cloud.ply").write_bytes(b"this is not a ply file")
    write_teacher(root / "no_trajectory", seed=8, trajectory=False)
    write_teacher(root / "no_psnr", seed=9, psnr=None)
    out = tmp_path / "out"
    report = build(settings(root, out, val_scenes=0))
    failed = {r.scene_id: r.error for r in report.failed}
    assert set(failed) == {"nan_means", "truncated"}
    dropped = {r.scene_id: r.reason for r in report.discovery.rejected + report.dropped}
    assert set(dropped) == {"garbage", "no_trajectory", "no_psnr"}
    text = summary(report)
    for name in ("nan_means", "truncated", "garbage", "no_trajectory", "no_psnr"):
        assert name in text
    keys = [k for k, _ in samples(out, "train")]
    assert sorted({k.split("__")[0] for k in keys}) == ["good0", "good1", "good2"] and len(keys) == 15
    assert not list(out.rglob(".tmp-*"))
    for path in (out / "train").glob("shard-*.tar"):  # no shard holds a sample of a bad teacher
        assert all(k.split("__")[0].startswith("good") for k, _ in shards.iter_shard(path))
    dropped_json = {d["scene"] for d in json.loads((out / "stats.json").read_text())["teachers"]["trainval"]["dropped"]}
    assert dropped_json == {"nan_means", "truncated", "garbage", "no_trajectory", "no_psnr"}
    # the CLI exits non-zero (EXIT_TEACHER_FAILED) but the good teachers' dataset is complete
    from scenesplat_stereo.cli import main

    rc = main(["build", "--teachers", str(root), "--out", str(out), "--samples-per-shard", "2", "--workers", "2",
               "--batch-pairs", "2", "--val-scenes", "0", "--no-progress"])
    assert rc == build_mod.EXIT_TEACHER_FAILED


def test_effects_touch_only_the_inputs_and_depth_is_the_expected_depth(built, teachers, tmp_path):
    out, _ = built
    fx = CameraEffects.parse("noise,vignetting,exposure", seed=3)
    build(settings(teachers, tmp_path / "fx", effects=fx, with_depth=True))
    plain, with_fx = samples(out, "train"), samples(tmp_path / "fx", "train")
    for (k0, m0), (k1, m1) in zip(plain, with_fx):
        assert k0 == k1
        assert m0["left.jpg"] != m1["left.jpg"] and m0["right.jpg"] != m1["right.jpg"]
        assert all(m0[n] == m1[n] for n in m0 if n.startswith(("target_", "mask_")))
        assert "left_depth.exr" in m1
    key, members = with_fx[0]
    meta = json.loads(members["json"])
    scene = load_ply(teachers / meta["scene"] / "point_cloud.ply")
    c2w = np.array([meta["c2w_left"]])
    render, alpha, _ = rasterization(**scene.to_torch(), viewmats=torch.from_numpy(viewmats_from_c2w(c2w)).float(),
                                     Ks=torch.tensor([meta["K"]], dtype=torch.float32), width=meta["width"],
                                     height=meta["height"], sh_degree=scene.sh_degree, render_mode="ED",
                                     rasterize_mode="antialiased")
    depth = decode_image(members["left_depth.exr"], "exr")[..., 0]
    want = render[0, ..., 0].numpy().astype(np.float16).astype(np.float32)
    assert np.array_equal(depth, want)
    assert (depth[alpha[0, ..., 0].numpy() > 0.5] > 2.0).all()  # the Gaussians sit 2.5-4 m away


def test_test_split_mode_and_max_frames(teachers, tmp_path):
    report = build(settings(teachers, tmp_path / "test", split_mode="test", max_frames=3, targets=3))
    got = samples(tmp_path / "test", "test")
    assert len(got) == 9 and report.planned == {"test": {"teachers": 3, "pairs": 9, "shards": 6}}
    frames = sorted({json.loads(m["json"])["frame"] for _, m in got})
    assert frames == [0, 2, 4]  # evenly spaced over 5 frames
    assert all(json.loads(m["json"])["target_ids"] == [0, 1, 2] for _, m in got)


def test_changed_settings_are_refused_and_removed_teachers_are_cleaned(teachers, tmp_path):
    root = write_teachers(tmp_path / "teachers")
    out = tmp_path / "out"
    build(settings(root, out))
    with pytest.raises(ValueError, match="resolution"):
        build(settings(root, out, resolution=(16, 12)))
    import shutil

    shutil.rmtree(root / "room0")
    with pytest.warns(UserWarning, match="does not plan"):
        report = build(settings(root, out))
    assert report.removed_stale > 0
    clean = tmp_path / "clean"
    build(settings(root, clean))
    assert tree(out) == tree(clean)


def test_ray_backend_gives_the_same_bytes(built, teachers, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is not installed (optional extra [ray])")
    out, _ = built
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        report = build(settings(teachers, tmp_path / "ray", backend="ray", workers=1))
    finally:
        ray.shutdown()
    assert not report.failed and len(report.results) == 3
    assert tree(tmp_path / "ray") == tree(out)


def test_ray_builds_teacher_after_teacher_in_one_gpu_worker(teachers, tmp_path, monkeypatch):
    """A teacher's Ray task that asks for a GPU runs in a worker that stays for the next teacher (Ray's default
    for GPU tasks is a fresh process each time: Python, torch, Warp, CUDA and nvJPEG paid per teacher). The GPU
    is a declared resource here; the teachers render on the CPU."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (optional extra [ray])")
    from scenesplat_stereo.build import run

    monkeypatch.setattr(run, "_ray_gpus", lambda settings: 1)
    ray.init(num_cpus=2, num_gpus=1, include_dashboard=False, log_to_driver=False)
    try:
        report = build(settings(teachers, tmp_path / "ray", backend="ray", workers=1))
    finally:
        ray.shutdown()
    assert not report.failed and len(report.results) == 3
    assert len({r.worker for r in report.results}) == 1, [r.worker for r in report.results]


@pytest.mark.real_data
def test_real_guitar_teacher_builds_at_tiny_size(guitar_ply, tmp_path):
    orbit = OrbitSpec(radius=6.0, n_frames=3, width=32, height=24)
    report = build(BuildSettings(teachers=guitar_ply.parent, out=tmp_path, min_psnr=None, orbit=orbit, val_scenes=0,
                                 targets=2, baseline=0.1, rho=0.2, progress=False, workers=2))
    assert not report.failed and report.planned["train"]["pairs"] == 3
    got = samples(tmp_path, "train")
    assert len(got) == 3
    for key, members in got:
        left = decode_image(members["left.jpg"], "jpg")
        mask = decode_image(members["mask_00.png"], "png")
        assert left.max() > 50 and 0 < (mask == 255).mean() < 1  # the guitar is in view, not the whole frame
        assert json.loads(members["json"])["teacher_psnr"] is None


def test_bench_build_runs_small_and_prints_the_tables(capsys, tmp_path):
    from scenesplat_stereo.cli import main

    out = tmp_path / "bench.md"
    assert main(["bench", "build", "--gaussians", "2000", "--sh-degree", "1", "--sizes", "32x24,48x36", "--pairs", "2",
                 "--frames", "3", "--workers", "2", "--batch-pairs", "2", "--qualities", "75", "--device", "cpu",
                 "--repeats", "2", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    for row in ("| base (RGB, q92, no effects, no depth), cpu JPEG, threads | 32x24 |",
                "| base (RGB, q92, no effects, no depth), cpu JPEG, processes | 48x36 |",
                "| JPEG quality 75 | 32x24 |", "| + left depth", "| + effects", "| threads | 1 |", "| processes | 2 |",
                "| 616x456 | 174,621 |", "| 1752x1168 | 149,196 |", "| **total** | 323,817 |", "cpu JPEG, encoder processes, from medians"):
        assert row in text, row
        assert row in out.read_text(), row
