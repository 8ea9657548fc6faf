"""Validation contact sheets (issue 36, class 7): at cpu-small's 64x64 the tiles are enlarged by whole pixels, and
each target shows the first render, the render now and the error, with the PSNR then and now in the caption."""

from __future__ import annotations

import math

import numpy as np
import torch

from scenesplat_stereo.shards.encode import decode_image
from sgmodel.metrics import sheets


def sample(render_offset: float, first_offset: float, size: int = 64, targets: int = 3) -> tuple[dict, dict]:
    g = torch.Generator().manual_seed(0)
    target = torch.rand(targets, 3, size, size, generator=g) * 0.5 + 0.25
    s = {"left": target[0], "depth": torch.full((1, size, size), 2.0), "targets": target,
         "renders": target + render_offset, "key": "room_00__000003", "step": 40}
    return s, {"step": 0, "renders": [target + first_offset]}


def test_small_tiles_are_enlarged_and_show_first_render_render_and_error():
    s, first = sample(0.1, 0.2)
    png = sheets.validation_sheet([s], first)
    img = decode_image(png, "png")
    factor = math.ceil(sheets.MIN_TILE / 64)  # 3: the short side reaches 160 px by whole pixels
    tile = 64 * factor
    tiles = 2 + 4 * sheets.SHEET_TARGETS  # left, depth, then target | step 0 | step 40 | error per target
    assert img.shape == (sheets.LABEL_H + tile + sheets.GAP, tiles * (tile + sheets.GAP), 3)
    body = img[sheets.LABEL_H:sheets.LABEL_H + tile]
    x = lambda k: k * (tile + sheets.GAP)  # noqa: E731  the left edge of tile k
    target = (s["targets"][0].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
    assert np.array_equal(body[:factor, x(2):x(2) + factor], np.broadcast_to(target[0, 0], (factor, factor, 3)))
    assert np.array_equal(body[::factor, x(2):x(2) + tile:factor], target)  # every pixel repeated, nothing smoothed
    then = np.clip(target.astype(int) + 51, 0, 255)  # the first render: target + 0.2
    assert np.abs(body[::factor, x(3):x(3) + tile:factor].astype(int) - then).max() <= 1
    # the error tile: |0.1| x 4 = 0.4 everywhere, one inferno colour
    error = body[:, x(5):x(5) + tile]
    assert (error == error[0, 0]).all() and not (error[0, 0] == 0).all()


def test_the_psnr_in_the_caption_is_the_image_psnr():
    s, first = sample(0.1, 0.2)
    assert abs(sheets.target_psnr(s["renders"][0], s["targets"][0]) - 20.0) < 1e-3  # mse 0.01: 20 dB
    assert abs(sheets.target_psnr(first["renders"][0][0], s["targets"][0]) - 10 * math.log10(1 / 0.04)) < 1e-3


def test_large_tiles_are_not_enlarged():
    assert sheets.enlargement(256, 320) == 1 and sheets.enlargement(64, 64) == 3 and sheets.enlargement(80, 120) == 2
