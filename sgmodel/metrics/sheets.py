"""Contact sheets: what the model learned, as pictures a person can look at.

One row per sample: the left input, its stereo depth (colour-mapped), then each target next to its
render. Labels are drawn with OpenCV; the PNG is encoded by ``scenesplat_stereo.shards.encode`` (the one owner
of image files). Used by validation during training and by ``sgmodel eval`` (worst and best targets).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from scenesplat_stereo.shards.encode import encode_png

GAP = 2  # pixels between tiles
LABEL_H = 14  # pixels of the caption band above each row


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


def labelled_row(tiles: list[np.ndarray], text: str) -> np.ndarray:
    h = max(t.shape[0] for t in tiles)
    pad = [np.pad(t, ((0, h - t.shape[0]), (0, GAP), (0, 0)), constant_values=255) for t in tiles]
    body = np.concatenate(pad, axis=1)
    return np.concatenate([_caption(body.shape[1], text), body], axis=0)


def stack_rows(rows: list[np.ndarray]) -> np.ndarray:
    w = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, GAP), (0, w - r.shape[1]), (0, 0)), constant_values=255) for r in rows])


def validation_sheet(samples: list[dict]) -> bytes:
    """PNG bytes; each sample: left [3,H,W], depth [1,H,W] metres, targets and renders [T,3,H,W], key."""
    if not samples:
        raise ValueError("validation_sheet: no samples")
    rows = []
    for s in samples:
        tiles = [tile(s["left"]), depth_png(s["depth"][0].cpu().numpy())]
        for target, render in zip(s["targets"], s["renders"]):
            tiles += [tile(target), tile(render)]
        rows.append(labelled_row(tiles, f"{s['key']}: left | depth | (target | render) x {len(s['targets'])}"))
    return encode_png(stack_rows(rows))


def target_sheet(entries: list[dict]) -> bytes:
    """PNG bytes of single targets (eval's worst and best): each entry target, render [3,H,W], caption."""
    if not entries:
        raise ValueError("target_sheet: no entries")
    return encode_png(stack_rows([labelled_row([tile(e["target"]), tile(e["render"])], e["caption"]) for e in entries]))
