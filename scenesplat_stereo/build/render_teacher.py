"""Render a teacher to PNG images: its own trajectory, or an orbit around its median.

SOURCE is a teacher folder (any layout of SPEC section 3: its trajectory and intrinsics are used) or a
single scene file in any format ``scene_files.load_scene`` reads (``.ply``, ``.compressed.ply``, ``.spz``,
``.sog``, a SOG's ``meta.json``, a streamed scene's ``lod-meta.json`` at its finest level, ``.splat``;
rendered along ``--orbit``). Images are rendered antialiased with the teacher's own
SH degree on a black background and written as 8-bit sRGB-agnostic PNGs ``OUT/frame_<k>.png`` (k in
trajectory order), plus ``OUT/alpha_<k>.png`` with ``--alpha``. Cameras are OpenCV; orbit radius is in
the scene's world units.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.common.ownership import StagedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import argtype, parse_size, whole_number
from scenesplat_stereo.raster import check_device, rasterization, tile_size_for
from scenesplat_stereo.scene.cameras import scale_intrinsics, viewmats_from_c2w
from scenesplat_stereo.scene.scene_files import load_scene
from scenesplat_stereo.scene.teachers import (OrbitSpec, Teacher, discover_teachers, resolve_trajectory,
                                              scene_file_teacher)
from scenesplat_stereo.shards.encode import encode_png

OWNER = "scenesplat-stereo render"  # recorded in OUT's manifest: a later render may replace OUT as a whole


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path, help="a teacher folder, or a scene file (.ply, .compressed.ply, .spz, .sog, "
                   "meta.json, lod-meta.json, .splat; then --orbit is used)")
    p.add_argument("--out", type=Path, required=True, help="output folder for frame_<k>.png (replaced as a whole: new, empty or an "
                   "earlier render's)")
    p.add_argument("--orbit", type=argtype(OrbitSpec.parse, "--orbit"),
                   default="radius=6,frames=8,size=640x480",
                   help="orbit for a scene file or a teacher without trajectory: 'radius=R,frames=N,elevation=DEG,"
                        "size=WxH,fov=DEG,up=-y' (radius in world units; default %(default)s)")
    p.add_argument("--lod", type=whole_number("--lod", 0), default=0,
                   help="level of a streamed SOG scene (lod-meta.json) to render: 0, the finest, by default "
                   "(other formats have one level)")
    p.add_argument("--max-frames", type=whole_number("--max-frames"), default=None, help="render only the first N frames")
    p.add_argument("--resolution", type=argtype(parse_size, "--resolution"), default=None, metavar="WxH",
                   help="render size in pixels (intrinsics rescaled)")
    p.add_argument("--rasterize-mode", default="antialiased", choices=("classic", "antialiased"),
                   help="antialiased (default, as the dataset) or classic 3DGS")
    p.add_argument("--alpha", action="store_true", help="also write alpha_<k>.png (8-bit opacity)")
    p.add_argument("--batch", type=whole_number("--batch"), default=4, help="cameras per rasterization call")
    p.add_argument("--device", type=argtype(check_device, "--device"),
                   default="cuda" if torch.cuda.is_available() else "cpu", help="cpu or cuda")


def _teacher_for(source: Path, orbit: OrbitSpec) -> Teacher:
    """The teacher of SOURCE; ValueError naming SOURCE and the reason when it is none."""
    if not source.exists():
        raise ValueError(f"SOURCE {source}: no such file or folder")
    if source.is_file():
        try:
            return scene_file_teacher(source, orbit)
        except ValueError as e:
            raise ValueError(f"SOURCE {e}") from None
    found = discover_teachers(source, orbit)
    if not found.teachers:
        reason = found.rejected[0].reason if found.rejected else "no teacher layout found"
        raise ValueError(f"SOURCE {source}: {reason}")
    return found.teachers[0]


def run(args: argparse.Namespace) -> int:
    """CLI entry: an unusable input raises a ValueError naming the flag or file before anything is written."""
    check_replaceable(args.out, "--out", OWNER)  # new, empty, or an earlier render's files only
    check_apart(args.out, "--out", {"SOURCE": args.source}, replaced=True)
    teacher = _teacher_for(args.source, args.orbit)
    scene = load_scene(teacher.ply_path, lod=args.lod)
    teacher = resolve_trajectory(teacher, scene.means)
    c2w, Ks, width, height = teacher.c2w, teacher.Ks, teacher.width, teacher.height
    if args.resolution:
        Ks = np.stack([scale_intrinsics(K, (width, height), args.resolution) for K in Ks])
        width, height = args.resolution
    if args.max_frames:
        c2w, Ks = c2w[: args.max_frames], Ks[: args.max_frames]
    g = scene.to_torch(args.device)
    viewmats = torch.tensor(viewmats_from_c2w(c2w), dtype=torch.float32, device=args.device)
    Ks_t = torch.tensor(Ks, dtype=torch.float32, device=args.device)
    t0 = time.perf_counter()
    with StagedFolder(args.out, OWNER) as tmp, torch.no_grad(), tqdm(total=len(c2w), unit="frame", desc=teacher.scene_id) as bar:
        for i in range(0, len(c2w), args.batch):
            img, alpha, _ = rasterization(
                g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], viewmats[i:i + args.batch],
                Ks_t[i:i + args.batch], width, height, sh_degree=scene.sh_degree,
                rasterize_mode=args.rasterize_mode, tile_size=tile_size_for(args.device),
            )
            for k in range(img.shape[0]):
                atomic_write_bytes(tmp / f"frame_{i + k:04d}.png", encode_png(img[k].cpu().numpy()))
                if args.alpha:
                    atomic_write_bytes(tmp / f"alpha_{i + k:04d}.png",
                                       encode_png(alpha[k].cpu().numpy()))
            bar.update(img.shape[0])
    dt = time.perf_counter() - t0
    print(f"{teacher.scene_id}: {len(c2w)} frames {width}x{height}, {len(scene):,} Gaussians, SH {scene.sh_degree}, "
          f"{dt:.1f} s ({len(c2w) / dt:.2f} frames/s) -> {args.out}", file=sys.stderr)
    return 0
