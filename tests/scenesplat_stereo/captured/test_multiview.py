"""``scenesplat-stereo import multiview`` against a line set whose truth is known, and on a real Middlebury set.

The synthetic set: a fronto-parallel textured plane at depth Z seen by five cameras on one line (views 0..4,
the pair (1, 3), positions p_k = (k - 1) / 2 in units of the baseline B). From the definition of a rectified
line, a camera moved by p B to the right sees the plane's texture moved left by p d pixels, d = f B / Z the
disparity between the pair's views: view k is the texture cut at a column offset of p_k d (whole pixels), so
the images, the expected masks and the poses all follow from the format description, not from our code.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from scenesplat_stereo.shards.sample import SampleMeta
from scenesplat_stereo.captured.multiview import BESIDE, BETWEEN, import_multiview, target_masks, view_positions
from scenesplat_stereo.cli import main as cli_main
from scenesplat_stereo.shards.webdataset import iter_shard
from scenesplat_stereo.shards.encode import encode_png

FOCAL, BASELINE, DISPARITY, SIZE = 40.0, 0.1, 4, 48  # px, m, px between the pair, W = H
PAIR, VIEWS, MARGIN = (1, 3), 5, 8
POSITIONS = [(k - PAIR[0]) / (PAIR[1] - PAIR[0]) for k in range(VIEWS)]  # -0.5, 0, 0.5, 1, 1.5


def texture(width: int, height: int) -> np.ndarray:
    """A smooth colour texture [H, W, 3] uint8 (sums of sinusoids, values within 25..230)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    channels = [0.5 + 0.2 * np.sin(x / 3.1 + c) * np.cos(y / 4.3 - c) + 0.15 * np.sin((x + 2 * y) / 7.0 + 2 * c)
                for c in range(3)]
    return np.clip(np.stack(channels, -1) * 255, 0, 255).round().astype(np.uint8)


def write_line_set(folder, disparity_scale: float = 8.0, with_disparity: bool = True):
    """Views im0..im4 of the plane (view k at column offset MARGIN + p_k d of the texture) and disp1.png."""
    folder.mkdir(parents=True)
    tex = texture(SIZE + 2 * MARGIN, SIZE)
    views = []
    for k, p in enumerate(POSITIONS):
        start = MARGIN + int(p * DISPARITY)
        views.append(tex[:, start:start + SIZE])
        (folder / f"im{k}.png").write_bytes(encode_png(np.ascontiguousarray(views[-1])))
    if with_disparity:
        disp = np.full((SIZE, SIZE, 1), DISPARITY * disparity_scale, dtype=np.uint8)
        (folder / f"disp{PAIR[0]}.png").write_bytes(encode_png(disp))
    return views


@pytest.fixture(scope="module")
def line_import(tmp_path_factory):
    root = tmp_path_factory.mktemp("multiview") / "root"
    views = write_line_set(root / "plane")
    out = root.parent / "out"
    report = import_multiview(root, out, FOCAL, BASELINE, PAIR)
    return root, out, views, report


def records(out):
    return [(key, SampleMeta.from_json(m["json"], key), m) for key, m in iter_shard(next((out / "test").glob("*.tar")))]


def test_record_holds_the_flagged_calibration_and_poses(line_import):
    _, out, _, report = line_import
    [(key, meta, members)] = records(out)
    assert key == "plane__000001" and meta.frame == PAIR[0] and meta.subset == "multiview"
    assert (meta.width, meta.height) == (SIZE, SIZE)
    np.testing.assert_array_equal(meta.K, [[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1]])
    assert meta.baseline == BASELINE
    np.testing.assert_array_equal(meta.c2w_left, np.eye(4))
    right = np.eye(4)
    right[0, 3] = BASELINE
    np.testing.assert_allclose(meta.c2w_right, right, atol=1e-15)
    assert meta.target_frames == (0, 2, 4) and meta.target_ids == (0, 1, 2)
    assert meta.target_groups == (BESIDE, BETWEEN, BESIDE)
    for c2w, k in zip(meta.targets, meta.target_frames):
        expected = np.eye(4)
        expected[0, 3] = POSITIONS[k] * BASELINE
        np.testing.assert_allclose(c2w, expected, atol=1e-15)
    assert meta.rho == pytest.approx(1.5 * BASELINE)
    assert sorted(members) == ["json", "left.jpg", "mask_00.png", "mask_01.png", "mask_02.png", "right.jpg",
                               "target_00.jpg", "target_01.jpg", "target_02.jpg"]
    bench = json.loads((out / "benchmark.json").read_text())
    assert bench["masked"] is False and bench["source"] == "captured"
    assert report["sets"][0]["groups"] == [BESIDE, BETWEEN, BESIDE]


def test_masks_mark_the_target_pixels_the_left_view_sees():
    """Constant disparity d: view k at column x sees the left view's column x + p d, so it is valid for
    0 <= x + p d <= W - 1 (written out per position, not through the splat)."""
    d = np.full((6, 20), 4.0)
    masks = target_masks(d, np.array([-0.5, 0.5, 1.5]))
    expected = np.zeros((3, 6, 20), dtype=bool)
    expected[0][:, 2:] = True     # x - 2 >= 0
    expected[1][:, :18] = True    # x + 2 <= 19
    expected[2][:, :14] = True    # x + 6 <= 19
    np.testing.assert_array_equal(masks, expected)
    # p = 1: a foreground (d = 10, columns 1..9; column 0 unknown) lands left of the image, the background
    # (d = 2, columns 10..19) on 8..17; the step between them is an occlusion edge, not a surface to fill
    step = np.full((1, 20), 2.0)
    step[0, :10] = 10.0
    step[0, 0] = 0.0
    [mask] = target_masks(step, np.array([1.0]))[:, 0]
    np.testing.assert_array_equal(np.flatnonzero(mask), np.arange(8, 18))


def test_naive_gs_with_the_true_depth_renders_the_held_out_views(line_import):
    """Exact depth z = f B / d: naive-GS into each target reproduces it where it is valid; the same render
    with the targets mirrored (the sign convention wrong) does not."""
    from sgmodel.metrics import image as metrics
    from sgmodel.data.loader import eval_batches
    from sgmodel.model import baselines
    from sgmodel.model.render import render_views

    _, out, _, _ = line_import
    [batch] = list(eval_batches(out, "test", 1, SIZE))
    z = torch.full((1, 1, SIZE, SIZE), FOCAL * BASELINE / DISPARITY)
    gaussians = baselines.naive_gs(batch["left"], z, batch["K"])
    mirrored = batch["target_viewmats"].clone()
    mirrored[..., 0, 3] *= -1
    right, wrong = (render_views(gaussians, v, batch["target_Ks"], SIZE, SIZE)[0][0].clamp(0, 1)
                    for v in (batch["target_viewmats"], mirrored))
    masks = batch["masks"][0]
    good = metrics.psnr(right, batch["targets"][0], masks)
    bad = metrics.psnr(wrong, batch["targets"][0], masks)
    assert (good > 30).all(), good
    assert (good - bad > 8).all(), (good, bad)
    assert batch["target_groups"] == [[BESIDE, BETWEEN, BESIDE]]


def test_eval_reports_between_and_beside(line_import, tmp_path, capsys):
    from sgmodel.cli import main as sg_main

    _, out, _, _ = line_import
    report = tmp_path / "eval"
    argv = ["eval", "--data", f"Line={out}", "--split", "test", "--method", "naive-gs", "--method", "forward-splat",
            "--encoder", "sgbm", "--resolution", str(SIZE), "--out", str(report), "--device", "cpu", "--no-progress"]
    assert sg_main(argv) == 0
    metrics_json = json.loads((report / "Line" / "naive-gs" / "metrics.json").read_text())
    assert metrics_json["group_targets"] == {BESIDE: 2, BETWEEN: 1}
    rows = (report / "Line" / "naive-gs" / "targets.csv").read_text().splitlines()
    assert rows[0].startswith("key,scene,target,group,") and len(rows) == 4
    means = {g: metrics_json["groups"][g]["psnr"] for g in (BESIDE, BETWEEN)}
    per_target = [float(r.split(",")[rows[0].split(",").index("psnr")]) for r in rows[1:]]
    assert means[BETWEEN] == pytest.approx(per_target[1]) and means[BESIDE] == pytest.approx(
        (per_target[0] + per_target[2]) / 2)
    table = (report / "table2.md").read_text().splitlines()[0]
    assert "Line PSNR" in table and "Line between PSNR" in table and "Line beside PSNR" in table
    assert "(between)" in (report / "Line" / "naive-gs" / "scenes.md").read_text()


def test_views_are_evenly_spaced_unless_given():
    np.testing.assert_array_equal(view_positions(9, (2, 6)), (np.arange(9) - 2) / 4)
    np.testing.assert_array_equal(view_positions(4, (0, 1), [0, 1, 2.5, 4]), [0, 1, 2.5, 4])


def test_cli_without_disparity_marks_every_pixel_and_replaces_an_earlier_import(tmp_path, capsys):
    write_line_set(tmp_path / "set", with_disparity=False)
    out = tmp_path / "out"
    argv = ["import", "multiview", str(tmp_path / "set"), "--out", str(out), "--focal", str(FOCAL), "--baseline",
            str(BASELINE), "--pair", "1,3"]
    assert cli_main(argv) == 0
    assert "no (masks all valid)" in capsys.readouterr().out
    [(_, meta, members)] = records(out)
    from scenesplat_stereo.shards.encode import decode_image
    assert all((decode_image(members[f"mask_{j:02d}.png"], "png") == 255).all() for j in meta.target_ids)
    assert cli_main(argv[:-1] + ["1,2"]) == 0  # an earlier import is replaced
    [(key, meta, _)] = records(out)
    assert meta.target_frames == (0, 3, 4) and meta.target_groups == (BESIDE, BESIDE, BESIDE)


@pytest.mark.real_data
def test_a_middlebury_set_is_rendered_better_by_its_geometry(shared_data, tmp_path):
    """barn1 at 64x64: naive-GS on the ground-truth disparity beats the targets mirrored (the wrong sign of the
    offsets) in every target, and the left image itself (no parallax) in the targets at least half a baseline
    away (nearer ones move by under half a pixel at this size, less than naive-GS's own blur)."""
    import cv2

    from sgmodel.metrics import image as metrics
    from sgmodel.data.loader import eval_batches
    from sgmodel.data.square_crop import SquareCrop
    from sgmodel.model import baselines
    from sgmodel.model.geometry import depth_from_disparity
    from sgmodel.model.render import render_views

    folder = shared_data / "multiview" / "middlebury2001-barn1"
    if not folder.is_dir():
        pytest.skip(f"shared data not available: {folder} is absent")
    out = tmp_path / "out"
    report = import_multiview(folder, out, 450.0, 0.065)
    assert report["sets"][0]["image_size"] == [432, 381]
    S = 64
    [batch] = list(eval_batches(out, "test", 1, S))
    assert batch["target_groups"] == [[BESIDE, BESIDE, BETWEEN, BETWEEN, BETWEEN, BESIDE, BESIDE]]
    raw = cv2.imread(str(folder / "disp2.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 8
    crop = SquareCrop.plan(raw.shape[1], raw.shape[0], S)
    disparity = torch.from_numpy(crop.nearest(raw) * crop.scaled_width / raw.shape[1])[None, None]
    z = depth_from_disparity(disparity, batch["K"][:, 0, 0], batch["baseline"])
    gaussians = baselines.naive_gs(batch["left"], z, batch["K"])
    mirrored = batch["target_viewmats"].clone()
    mirrored[..., 0, 3] *= -1
    right, wrong = (render_views(gaussians, v, batch["target_Ks"], S, S)[0][0].clamp(0, 1)
                    for v in (batch["target_viewmats"], mirrored))
    targets, masks = batch["targets"][0], batch["masks"][0]
    still = batch["left"].expand_as(targets)
    good, bad = metrics.psnr(right, targets, masks), metrics.psnr(wrong, targets, masks)
    positions = report["sets"][0]["positions"]
    far = torch.tensor([abs(positions[k]) >= 0.5 for k in report["sets"][0]["target_views"]])
    assert (good > bad).all(), (good, bad)
    assert (good > metrics.psnr(still, targets, masks))[far].all(), good
