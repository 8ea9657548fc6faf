"""A contact sheet of composed teachers (``scenesplat-stereo compose-teachers``): per teacher, frames looking at
the object, one looking past it into the room, and the first frame's rendered depth (turbo on inverse depth, red
near, blue far), captioned with the scale family, the object's size and the camera distances.

``python scripts/figures/composed_teachers.py TEACHERS OUT.png [--thumb 128x96] [--frames 3]`` renders on the
GPU when there is one, else on the CPU (a few seconds a teacher at the default size), antialiased, the
teacher's own SH degree.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.common.text import argtype, parse_size
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.scene.cameras import scale_intrinsics, viewmats_from_c2w
from scenesplat_stereo.scene.gaussians import load_ply
from scenesplat_stereo.scene.teachers import discover_teachers
from scenesplat_stereo.shards.encode import encode_png
from sgmodel.metrics.sheets import depth_png, labelled_row, stack_rows


def teacher_row(teacher, thumb: tuple[int, int], n_look: int, device: str) -> np.ndarray:
    """One captioned row: ``n_look`` frames looking at the object, one looking past it, the first one's depth."""
    frames = json.loads((teacher.ply_path.parent / "transforms.json").read_text())["frames"]
    looking = [i for i, f in enumerate(frames) if f.get("looks_at_object", True)]
    past = [i for i, f in enumerate(frames) if not f.get("looks_at_object", True)]
    picks = [looking[int(k)] for k in np.linspace(0, len(looking) - 1, n_look).round()] + past[:1]
    scene = load_ply(teacher.ply_path)
    g = scene.to_torch(device)
    K = scale_intrinsics(teacher.Ks[picks], (teacher.width, teacher.height), thumb)
    with torch.no_grad():
        img, _, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                  torch.tensor(viewmats_from_c2w(teacher.c2w[picks]), dtype=torch.float32, device=device),
                                  torch.tensor(K, dtype=torch.float32, device=device), thumb[0], thumb[1],
                                  sh_degree=scene.sh_degree, render_mode="RGB+ED", rasterize_mode="antialiased")
    img = img.cpu().numpy()
    tiles = [(np.clip(i[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8) for i in img]
    tiles.append(depth_png(img[0, ..., 3]))
    meta = json.loads((teacher.ply_path.parent / "scene.json").read_text())
    text = (f"{teacher.scene_id}: {meta['object_size_m']:.2f} m seen from {meta['distance_m'][0]:.1f}-"
            f"{meta['distance_m'][1]:.1f} m")
    return labelled_row(tiles, text)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("teachers", type=Path)
    p.add_argument("out", type=Path, help="PNG file")
    p.add_argument("--thumb", type=argtype(parse_size, "--thumb"), default="128x96", metavar="WxH")
    p.add_argument("--frames", type=int, default=3, help="frames looking at the object per teacher (default 3)")
    args = p.parse_args()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    teachers = discover_teachers(args.teachers).teachers
    rows = [teacher_row(t, args.thumb, args.frames, device) for t in teachers]
    atomic_write_bytes(args.out, encode_png(stack_rows(rows)))
    print(f"{len(rows)} teachers -> {args.out} ({args.out.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
