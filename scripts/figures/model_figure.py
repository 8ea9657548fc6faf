"""docs/images/prediction.png: one prediction of a trained model, as pictures.

``python scripts/figures/model_figure.py CKPT LEFT RIGHT CALIB OUT.png [--device cuda]``. Rows: the input pair and
the stereo depth; the front layer alone, the back layer alone and both, rendered from the left camera; the
whole scene from four novel views around it (left, right, up, forward by 10% of the median depth).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.shards.encode import decode_image, encode_png
from sgmodel.metrics.sheets import depth_png, labelled_row, stack_rows, tile
from sgmodel.model.network import load_predictor
from sgmodel.model.render import render_views
from sgmodel.pairs.calib import read_calib
from sgmodel.predict.export import novel_view_cameras


def _read(path: str, device: str) -> torch.Tensor:
    img = decode_image(Path(path).read_bytes(), Path(path).suffix)
    return torch.from_numpy(img[..., :3].copy()).permute(2, 0, 1)[None].float().div(255).to(device)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for name in ("checkpoint", "left", "right", "calib", "out"):
        p.add_argument(name)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args()
    predictor = load_predictor(args.checkpoint, args.device)
    left, right = _read(args.left, args.device), _read(args.right, args.device)
    _, _, H, W = left.shape
    calib = read_calib(Path(args.calib))
    K = torch.tensor(calib.K, dtype=torch.float32, device=args.device)[None]
    with torch.no_grad():
        out = predictor.model(left, right, K, torch.tensor([calib.baseline], device=args.device))
        g, n = out.gaussians, out.gaussians["means"].shape[1]
        half = {k: v[:, : n // 2] for k, v in g.items()}, {k: v[:, n // 2:] for k, v in g.items()}
        eye = torch.eye(4, device=args.device)[None, None]
        layers = [render_views(x, eye, K[:, None], W, H)[0][0, 0] for x in (*half, g)]
        focus = float(out.depth[out.depth < 10].median()) if (out.depth < 10).any() else 2.0
        views = novel_view_cameras(0.1 * focus, focus)
        names = ["left", "right", "up", "forward"]
        view = torch.tensor(np.stack([views[v] for v in names]), dtype=torch.float32,
                            device=args.device)[None]
        novel = render_views(g, view, K[:, None].expand(1, 4, 3, 3), W, H)[0][0]
    rows = [labelled_row([tile(left[0]), tile(right[0]), depth_png(out.depth[0, 0].cpu().numpy())],
                 "input left | input right | stereo depth (near red, far blue)"),
            labelled_row([tile(x) for x in layers], "front layer | back layer | both (left camera)"),
            labelled_row([tile(x) for x in novel], "novel views: " + " | ".join(names))]
    atomic_write_bytes(Path(args.out), encode_png(stack_rows(rows)))


if __name__ == "__main__":
    main()
