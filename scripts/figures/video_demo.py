"""A stereo video rendered from a demo teacher room, run through ``sgmodel predict --video``, and a contact
sheet of its frames (the README's video demo, docs/images/video_demo.png).

    python scripts/figures/video_demo.py OUT [--frames 24] [--size 256x192] [--sheet docs/images/video_demo.png]

``render_clip`` renders a rectified stereo camera (baseline 0.1 m) moving slowly through
``scenesplat_stereo.build.demo``'s room 0 with the project's rasteriser and writes ``left.mkv``, ``right.mkv``
and ``sbs.mkv`` (FFV1, lossless, so a decoded frame is the rendered one) and ``K.txt``; tests/sgmodel/predict/test_video.py
uses it too. The demo then predicts naive-GS scenes on SGBM depth (no checkpoint needed) and renders a slow
orbit; the sheet shows, for four frames, the left input above the novel view.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from scenesplat_stereo.build.demo import make_room, room_trajectory
from scenesplat_stereo.common.text import parse_size
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.scene.cameras import right_camera
from scenesplat_stereo.shards.encode import encode_png, to_uint8
from sgmodel.cli import main as sgmodel

BASELINE = 0.1  # metres
#: The clip covers this share of the room's trajectory loop per frame (slow: neighbouring frames overlap),
#: from this frame of the loop on (where the table and the lamp stand in front of a wall).
LOOP_PER_FRAME, START = 1 / 400, 112


def render_clip(out: Path, frames: int, width: int, height: int, num_gaussians: int = 36_000) -> np.ndarray:
    """Write left.mkv, right.mkv, sbs.mkv (FFV1, 30 fps) and K.txt (FoundationStereo format) in ``out``;
    returns the rendered left frames, uint8 RGB [F, H, W, 3]."""
    out.mkdir(parents=True, exist_ok=True)
    scene = make_room(0, num_gaussians=num_gaussians).to_torch()
    c2w = room_trajectory(round(1 / LOOP_PER_FRAME))[START:START + frames]
    f = 0.8 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    writers = {name: cv2.VideoWriter(str(out / f"{name}.mkv"), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (w, height))
               for name, w in (("left", width), ("right", width), ("sbs", 2 * width))}
    lefts = []
    for pose in c2w:
        views = torch.tensor(np.stack([np.linalg.inv(pose), np.linalg.inv(right_camera(pose, BASELINE))]),
                             dtype=torch.float32)
        rgb, _, _ = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                  scene["colors"], views, torch.tensor(K, dtype=torch.float32).expand(2, 3, 3),
                                  width, height, sh_degree=0)
        left, right = (to_uint8(rgb[i].clamp(0, 1).numpy()) for i in range(2))
        for name, img in (("left", left), ("right", right), ("sbs", np.concatenate([left, right], 1))):
            writers[name].write(np.ascontiguousarray(img[..., ::-1]))
        lefts.append(left)
    for w in writers.values():
        w.release()
    (out / "K.txt").write_text(" ".join(f"{v:.6f}" for v in K.flatten()) + f"\n{BASELINE}\n")
    return np.stack(lefts)


def read_frames(path: Path) -> np.ndarray:
    """Every frame of a video, uint8 RGB [F, H, W, 3]."""
    cap, frames = cv2.VideoCapture(str(path)), []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[..., ::-1])
    cap.release()
    return np.stack(frames)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--size", type=lambda s: parse_size(s, "--size"), default=(256, 192))
    p.add_argument("--sheet", type=Path, default=Path("docs/images/video_demo.png"))
    args = p.parse_args()
    lefts = render_clip(args.out / "clip", args.frames, *args.size)
    rc = sgmodel(["predict", "--video", str(args.out / "clip" / "sbs.mkv"), "--calib", str(args.out / "clip" / "K.txt"),
                  "--method", "naive-gs", "--encoder", "sgbm", "--resolution", str(min(args.size)),
                  "--trajectory", "orbit:0.15,1", "--codec", "ffv1", "--frames", "--out", str(args.out / "predict"),
                  "--device", "cpu"])
    if rc:
        return rc
    views = read_frames(args.out / "predict" / "novel_view.mkv")
    pick = np.linspace(0, len(views) - 1, 4).round().astype(int)
    sheet = np.concatenate([np.concatenate([lefts[i], views[i]], 0) for i in pick], 1)
    args.sheet.parent.mkdir(parents=True, exist_ok=True)
    args.sheet.write_bytes(encode_png(sheet))
    print(f"wrote {args.sheet}: frames {pick.tolist()}, left input above the novel view")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
