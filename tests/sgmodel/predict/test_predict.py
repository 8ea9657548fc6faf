"""``sgmodel predict`` end to end on a stereo pair rendered from the real guitar teacher, the export round
trip, and every bad input (exit 2, nothing written)."""

from __future__ import annotations

import argparse
import json
import math
import re

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.scene.gaussians import load_ply
from scenesplat_stereo.shards.encode import decode_image, encode_png
from scripts.inputs.guitar_pair import H, W, render_pair
from sgmodel.cli import main as sgmodel_main
from sgmodel.metrics.sheets import depth_png
from sgmodel.model.baselines import naive_gs
from sgmodel.predict import command as predict_mod
from sgmodel.predict.export import orbit_cameras, to_scene
from sgmodel.predict.scene_writers import write_scene
from tests.support.model_helpers import predict_status as run


class OracleEncoder:
    """A stand-in encoder that returns a given disparity (the small synthetic pairs' exact one)."""

    def __init__(self, disparity: torch.Tensor) -> None:
        self.disparity = disparity

    def __call__(self, left, right):
        assert left.shape[-2:] == self.disparity.shape[-2:]
        return argparse.Namespace(disparity=self.disparity, features=[])

    def max_disparity(self, width: int) -> float:
        return math.inf


@pytest.fixture(scope="module")
def guitar_pair(guitar_ply, tmp_path_factory):
    """Left/right PNGs of the guitar and a FoundationStereo K.txt (scripts/inputs/guitar_pair.py), K and the left
    view's alpha."""
    folder = tmp_path_factory.mktemp("guitar_pair")
    K, _, a = render_pair(guitar_ply, folder)
    assert 0.1 < (a > 0.5).float().mean() < 0.9, "the guitar should fill part of the frame"
    return folder, K, a


def test_predict_naive_gs_on_the_guitar_reproduces_the_left_image(guitar_pair, tmp_path, capsys):
    folder, K, alpha = guitar_pair
    out = tmp_path / "out"
    rc = run(["--left", folder / "left.png", "--right", folder / "right.png", "--calib", folder / "K.txt",
              "--method", "naive-gs", "--encoder", "sgbm", "--resolution", H, "--out", out, "--device", "cpu"])
    log = capsys.readouterr().out
    assert rc == 0, log
    assert "| encoder |" in log and "| render views |" in log and f"model size {W}x{H}" in log
    names = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert names == [".written-by", "cameras.json", "depth.png", "orbit.gif", "scene.ply", "settings.json"] + [
        f"views/{v}.png" for v in ("center", "down", "forward", "left", "right", "up")]
    scene = load_ply(out / "scene.ply", strict=True)
    dropped, produced, kept = (int(x.replace(",", "")) for x in re.search(
        r"([\d,]+) of ([\d,]+) Gaussians dropped: no valid stereo depth .*; ([\d,]+) kept", log).groups())
    assert produced == W * H and kept == produced - dropped == len(scene)
    assert scene.sh_degree == 0 and "SH degree 0" in log  # naive-GS has plain colours
    g = scene.to_torch()
    rgb, a, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                              torch.eye(4)[None], torch.tensor(K, dtype=torch.float32)[None], W, H, sh_degree=0)
    left = torch.from_numpy(decode_image((folder / "left.png").read_bytes(), "png")).float() / 255
    valid = alpha > 0.99

    def psnr(x):
        return -10 * math.log10(float(((x.clamp(0, 1) - left)[valid] ** 2).mean()))

    raw = psnr(rgb[0])
    print(f"guitar naive-GS left view: PSNR {raw:.2f} dB over {int(valid.sum())} valid pixels")
    assert raw > 25, raw
    depth = decode_image((out / "depth.png").read_bytes(), "png")
    assert depth.shape == (H, W, 3)
    inp = oiio.ImageInput.open(str(out / "orbit.gif"))
    n = 0
    while inp.seek_subimage(n, 0):
        n += 1
    inp.close()
    assert n == predict_mod.ORBIT_FRAMES


def test_export_round_trip_through_load_ply(tmp_path):
    g = torch.Generator().manual_seed(0)
    left = torch.rand(1, 3, 6, 7, generator=g)
    z = 0.5 + 3 * torch.rand(1, 1, 6, 7, generator=g)
    K = torch.tensor([[[50.0, 0, 3.5], [0, 55.0, 3.0], [0, 0, 1]]])
    gaussians = naive_gs(left, z, K)
    n = 42
    q = torch.randn(1, n, 4, generator=g)
    gaussians.update(quats=q / q.norm(dim=-1, keepdim=True), sh=torch.randn(1, n, 9, 3, generator=g),
                     opacities=torch.rand(1, n, generator=g) * 0.98 + 0.01,
                     scales=torch.rand(1, n, 3, generator=g) * 0.1 + 1e-3)
    scene = load_ply(write_scene(to_scene(gaussians), tmp_path / "s.ply"), strict=True)
    for name, key in (("means", "means"), ("quats", "quats"), ("scales", "scales"),
                      ("opacities", "opacities"), ("sh", "sh")):
        np.testing.assert_allclose(getattr(scene, name), gaussians[key][0].numpy(), rtol=2e-6, atol=2e-7,
                                   err_msg=name)


def test_depth_png_maps_near_to_red_and_far_to_blue():
    z = np.array([[1.0, 2.0, 4.0]])
    rgb = depth_png(z, near=1.0, far=4.0)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 3, 3)
    assert rgb[0, 0, 0] > rgb[0, 0, 2] and rgb[0, 2, 2] > rgb[0, 2, 0]


def test_orbit_cameras_look_at_the_focus():
    views = orbit_cameras(8, 0.5, 3.0)
    for v in views:
        c2w = np.linalg.inv(v)
        assert np.hypot(*c2w[:2, 3]) == pytest.approx(0.5) and c2w[2, 3] == pytest.approx(0.0)
        p = v @ np.array([0, 0, 3.0, 1])
        assert p[:2] == pytest.approx([0, 0], abs=1e-12) and p[2] == pytest.approx(math.hypot(3, 0.5))


@pytest.fixture()
def small_pair(tmp_path):
    img = (np.random.default_rng(0).random((32, 48, 3)) * 255).astype(np.uint8)
    for name in ("l.png", "r.png"):
        (tmp_path / name).write_bytes(encode_png(img))
    (tmp_path / "r_small.png").write_bytes(encode_png(img[:16]))
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    (tmp_path / "K.txt").write_text("50 0 24 0 50 16 0 0 1\n0.1\n")
    (tmp_path / "K_bad.txt").write_text("50 0 24 0 50 16 0 0\n0.1\n")
    (tmp_path / "mb.txt").write_text("cam0=[50 0 24; 0 50 16; 0 0 1]\nbaseline=100\nwidth=64\nheight=32\n")
    (tmp_path / "ckpt.pt").write_bytes(b"")
    return tmp_path


@pytest.mark.parametrize("change,message", [
    ({"--left": "missing.png"}, "--left .*missing.png: file not found"),
    ({"--right": "broken.png"}, "--right .*broken.png: not a readable image"),
    ({"--right": "K.txt"}, "--right .*K.txt: unsupported image type"),
    ({"--right": "r_small.png"}, "is 48x32 but --right .* is 48x16"),
    ({"--calib": "K_bad.txt"}, r"K_bad.txt: line 1 \(K\) must hold 9 numbers"),
    ({"--calib": "mb.txt"}, r"mb.txt: width=64, height=32 do not match .*l.png \(48x32\)"),
    ({"--calib": None, "--intrinsics": "0,50,24,16", "--baseline": "0.1"}, "--intrinsics: focal lengths"),
    ({"--calib": None, "--intrinsics": "50,50,24,16", "--baseline": "0"}, "--baseline: baseline must be positive"),
    ({"--calib": None}, "missing calibration"),
    ({"--intrinsics": "50,50,24,16", "--baseline": "0.1"}, "either --calib or --intrinsics"),
    ({"--checkpoint": "ckpt.pt"}, "--checkpoint CKPT or --method .*, not both"),
    ({"--method": None, "--checkpoint": "nope.pt"}, "--checkpoint .*nope.pt: file not found"),
    ({"--resolution": "8"}, "--resolution must be at least 16"),
    ({"--out": "K.txt"}, "--out .*K.txt: inside --calib .*K.txt; write outputs apart from the inputs"),
    ({"--out": "no/such/out"}, "--out .*: parent folder .* does not exist"),
    ({"--encoder": "no-such-encoder"}, "--encoder"),
])
def test_bad_inputs_exit_2_and_write_nothing(small_pair, capsys, monkeypatch, change, message):
    if "--encoder" in change:
        pytest.importorskip("sgmodel.encoders", reason="sgmodel.encoders is not in this tree yet")
    else:
        monkeypatch.setattr(predict_mod, "make_encoder",
                            lambda *a: OracleEncoder(torch.full((1, 1, 32, 48), 2.0)))
    args = {"--left": "l.png", "--right": "r.png", "--calib": "K.txt", "--method": "naive-gs", "--out": "out",
            "--device": "cpu", "--resolution": "32"}
    args.update(change)
    before = sorted(p.name for p in small_pair.iterdir())
    argv = [x for k, v in args.items() if v is not None for x in (k, v if k in ("--device", "--method",
            "--resolution", "--intrinsics", "--baseline", "--encoder") else small_pair / v)]
    assert run(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("sgmodel predict: error: ") and len(err.strip().splitlines()) == 1, err
    assert __import__("re").search(message, err), err
    assert sorted(p.name for p in small_pair.iterdir()) == before


def test_small_pair_at_another_size_and_forward_splat(small_pair, capsys, monkeypatch):
    monkeypatch.setattr(predict_mod, "make_encoder", lambda *a: OracleEncoder(torch.full((1, 1, 16, 32), 2.0)))
    out = small_pair / "fs"
    rc = run(["--left", small_pair / "l.png", "--right", small_pair / "r.png", "--intrinsics", "50,50,24,16",
              "--baseline", "0.1", "--method", "forward-splat", "--resolution", "20", "--out", out,
              "--device", "cpu"])
    log = capsys.readouterr().out
    assert rc == 0 and "model size 32x16" in log and "fx=33.33" in log, log
    assert not (out / "scene.ply").exists() and (out / "views" / "left.png").is_file()
    assert decode_image((out / "views" / "center.png").read_bytes(), "png").shape == (16, 32, 3)


def test_bench_predict_times_every_stage_on_the_cpu(tmp_path, capsys):
    from sgmodel.bench.predict import STAGES

    out = tmp_path / "bench.md"
    assert sgmodel_main(["bench", "predict", "--preset", "cpu-small", "--device", "cpu", "--size", "48x32",
                         "--warmup", "0", "--repeats", "1", "--out", str(out)]) == 0
    text = out.read_text()
    assert "One pair of 48x32" in text
    for stage in STAGES:
        assert re.search(rf"\| {re.escape(stage)} \| \d+\.\d \|", text), stage
    n = (48 + 2 * 4) * (32 + 2 * 4) * 2  # two layers on the padded canvas (cpu-small: padding 4)
    assert f"to {n:,} Gaussians" in text
    for scene in ("as predicted (0)", "2 (a trained model's)"):  # a fresh model: SH 0
        for fmt in ("ply", "compressed-ply", "spz", "ply, fsync'd"):
            assert re.search(rf"\| {re.escape(fmt)} \| {re.escape(scene)} \| [\d,]+ \| \d+\.\d \| \d+\.\d \| "
                             rf"\d+\.\d \| \d+\.\d\d \| \d+\.\d \|", text), (scene, fmt)
        assert re.search(rf"\| spz: its deflate alone \(zlib 6, one thread\) \| {re.escape(scene)} \| [\d,]+ \|", text)


def test_bench_predict_video_on_the_cpu(tmp_path):
    out = tmp_path / "bench.md"
    assert sgmodel_main(["bench", "predict", "--video", "--preset", "cpu-small", "--device", "cpu", "--size", "48x32",
                         "--frames", "5", "--batch-size", "2", "--warmup", "0", "--repeats", "2",
                         "--scene-formats", "spz", "spz-parallel", "--out", str(out)]) == 0
    text = out.read_text()
    assert "Stereo video of 48x32 per eye" in text and "5 frames in batches of 2" in text
    for row in (re.escape("model alone (encoder to Gaussians)"),
                re.escape("end to end (decode, model, one novel view, encode)"),
                *(re.escape(f"end to end (decode, model, one novel view, encode, a .spz scene per frame, format {fmt} "
                            "(writers busy") + r" \d+%\)\)" for fmt in ("spz", "spz-parallel"))):
        assert re.search(rf"\| {row} \| 2 \| [\d.]+ \| [\d.]+ \| [\d.]+ \|", text), row
    assert re.search(r"written in as many processes \(started in [\d.]+ s before the stream", text)


@pytest.mark.parametrize("flag,value", [("--scene-writers", "0"), ("--repeats", "0"), ("--frames", "-1"),
                                        ("--batch-size", "x"), ("--warmup", "-1")])
def test_bench_predict_refuses_a_bad_count_in_one_line(tmp_path, capsys, flag, value):
    out = tmp_path / "bench.md"
    with pytest.raises(SystemExit) as refused:  # argparse's refusal
        sgmodel_main(["bench", "predict", "--video", "--preset", "cpu-small", "--device", "cpu", flag, value,
                      "--out", str(out)])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and flag in err[0] and value in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("fmt,suffix", [("spz", ".spz"), ("compressed-ply", ".compressed.ply"), ("sog", ".sog")])
def test_predict_writes_the_chosen_format_and_viewer_files(small_pair, capsys, monkeypatch, fmt, suffix):
    d = torch.full((1, 1, 32, 48), 2.0)
    d[..., :4, :] = 0.0  # four rows without a match
    monkeypatch.setattr(predict_mod, "make_encoder", lambda *a: OracleEncoder(d))
    out = small_pair / fmt
    assert run(["--left", small_pair / "l.png", "--right", small_pair / "r.png", "--calib", small_pair / "K.txt",
                "--method", "naive-gs", "--resolution", "32", "--format", fmt, "--out", out, "--device", "cpu"]) == 0
    log = capsys.readouterr().out
    assert f"{4 * 48:,} of {32 * 48:,} Gaussians dropped" in log and "SH degree 0" in log
    from scenesplat_stereo.scene.scene_files import load_scene

    scene = load_scene(out / f"scene{suffix}")
    assert len(scene) == 28 * 48 and scene.sh_degree == 0
    assert scene.means[:, 2].max() < 2.6  # z = fx B / d = 50 * 0.1 / 2 = 2.5 m: nothing at the far clamp
    settings = json.loads((out / "settings.json").read_text())
    assert settings["cameras"][0]["initial"]["target"] == [0.0, 0.0, 2.5]  # the median valid depth
    depth = decode_image((out / "depth.png").read_bytes(), "png")
    assert not depth[:4].any() and depth[4:].any()  # black where there is no stereo depth
