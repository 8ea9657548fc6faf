"""Contact sheets: what the model learned, as pictures a person can look at.

Validation (``validation_sheet``): one row per sample, the left input and its stereo depth (colour-mapped), then for
each of its first ``SHEET_TARGETS`` targets: the target, the render of the run's first validation (step 0 of a new
run), the render now, and the error now (|render - target| averaged over channels, times ``ERROR_GAIN``, inferno:
black = right); each caption gives the PSNR then and now, so the picture shows what the numbers say. Tiles smaller
than ``MIN_TILE`` pixels on their short side (cpu-small trains at 64x64) are enlarged by whole pixels (nearest
neighbour: nothing is smoothed away). Labels are drawn with OpenCV; the PNG is encoded by
``scenesplat_stereo.shards.encode`` (the one owner of image files). Used by validation during training and by
``sgmodel eval`` (worst and best targets).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from scenesplat_stereo.common.measure import psnr_from_mse
from scenesplat_stereo.shards.encode import encode_png

GAP = 2  # pixels between tiles
LABEL_H = 14  # pixels of the caption band above each row
MIN_TILE = 160  # pixels: smaller tiles are enlarged by a whole factor up to at least this short side
SHEET_TARGETS = 2  # targets shown per validation sample (the sheet stays readable)
ERROR_GAIN = 4.0  # the error tile shows 4 x |render - target|: an error of 0.25 is white


def depth_png(z: np.ndarray, near: float | None = None, far: float | None = None,
              valid: np.ndarray | None = None) -> np.ndarray:
    """z-depth [H,W] metres -> uint8 RGB [H,W,3], turbo colour map on inverse depth.

    Legend: red = near, through yellow and green, to dark blue = far; black = no stereo depth (where
    ``valid`` [H,W] bool is False). near/far default to the 2nd and 98th percentiles of the valid z (values
    outside are clipped). Inverse depth spreads the colours like disparity does.
    """
    z = np.asarray(z, dtype=np.float64)
    known = z[valid] if valid is not None and valid.any() else z.ravel()
    near = float(np.percentile(known, 2)) if near is None else near
    far = float(np.percentile(known, 98)) if far is None else far
    far = max(far, near * (1 + 1e-6))
    t = (1.0 / np.clip(z, near, far) - 1.0 / far) / (1.0 / near - 1.0 / far)
    bgr = cv2.applyColorMap(np.rint(t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    rgb = np.ascontiguousarray(bgr[..., ::-1])
    if valid is not None:
        rgb[~valid] = 0
    return rgb


def tile(t: torch.Tensor) -> np.ndarray:
    """[3, H, W] in [0, 1] -> uint8 [H, W, 3]."""
    return (t.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def _caption(width: int, text: str) -> np.ndarray:
    band = np.full((LABEL_H, width, 3), 255, np.uint8)
    cv2.putText(band, text, (2, LABEL_H - 4), cv2.FONT_HERSHEY_PLAIN, 0.8, (0, 0, 0), 1, cv2.LINE_AA)
    return band


def enlarge(t: np.ndarray, factor: int) -> np.ndarray:
    """uint8 [H, W, 3] -> [factor H, factor W, 3], every pixel repeated (nearest neighbour)."""
    return t if factor == 1 else np.repeat(np.repeat(t, factor, axis=0), factor, axis=1)


def enlargement(height: int, width: int) -> int:
    """The whole factor that brings a tile's short side to at least ``MIN_TILE`` pixels (1 for large tiles)."""
    return max(1, -(-MIN_TILE // max(1, min(height, width))))


def error_tile(render: torch.Tensor, target: torch.Tensor) -> np.ndarray:
    """|render - target| [3,H,W] averaged over channels, times ``ERROR_GAIN``, as an inferno image (black: no
    error, white: ``1 / ERROR_GAIN`` or more)."""
    err = ((render.detach().float() - target.detach().float()).abs().mean(0) * ERROR_GAIN).clamp(0, 1)
    grey = (err.cpu().numpy() * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(cv2.applyColorMap(grey, cv2.COLORMAP_INFERNO)[..., ::-1])


def target_psnr(render: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR (dB) of a render [3,H,W] against its target over the whole image, both clipped to [0, 1]."""
    mse = (render.detach().float().clamp(0, 1) - target.detach().float().clamp(0, 1)).pow(2).mean().item()
    return psnr_from_mse(mse)


def labelled_row(tiles: list[np.ndarray], text: str) -> np.ndarray:
    h = max(t.shape[0] for t in tiles)
    pad = [np.pad(t, ((0, h - t.shape[0]), (0, GAP), (0, 0)), constant_values=255) for t in tiles]
    body = np.concatenate(pad, axis=1)
    return np.concatenate([_caption(body.shape[1], text), body], axis=0)


def stack_rows(rows: list[np.ndarray]) -> np.ndarray:
    w = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, GAP), (0, w - r.shape[1]), (0, 0)), constant_values=255) for r in rows])


def validation_sheet(samples: list[dict], first: dict | None = None) -> bytes:
    """PNG bytes; each sample: left [3,H,W], depth [1,H,W] metres, targets and renders [T,3,H,W], key, and the
    step. ``first``: {"step": s0, "renders": [renders [T,3,H,W] of each sample]} of the run's first validation
    (the same samples, in order); None draws the first validation itself."""
    if not samples:
        raise ValueError("validation_sheet: no samples")
    rows = []
    for n, s in enumerate(samples):
        factor = enlargement(*s["left"].shape[-2:])
        then = first["renders"][n] if first is not None else s["renders"]
        s0 = first["step"] if first is not None else s["step"]
        tiles = [tile(s["left"]), depth_png(s["depth"][0].cpu().numpy())]
        psnrs = []
        for target, old, render in list(zip(s["targets"], then, s["renders"]))[:SHEET_TARGETS]:
            tiles += [tile(target), tile(old), tile(render), error_tile(render, target)]
            psnrs.append(f"{target_psnr(old, target):.1f}->{target_psnr(render, target):.1f} dB")
        text = (f"{s['key']}: left | depth | (target | step {s0} | step {s['step']} | error x{ERROR_GAIN:g}) "
                f"x {min(len(s['targets']), SHEET_TARGETS)} of {len(s['targets'])}; PSNR {', '.join(psnrs)}")
        rows.append(labelled_row([enlarge(t, factor) for t in tiles], text))
    return encode_png(stack_rows(rows))


def target_sheet(entries: list[dict]) -> bytes:
    """PNG bytes of single targets (eval's worst and best): each entry target, render [3,H,W], caption."""
    if not entries:
        raise ValueError("target_sheet: no entries")
    return encode_png(stack_rows([labelled_row([tile(e["target"]), tile(e["render"])], e["caption"]) for e in entries]))
