"""Camera poses for IRS scene variants (paper appendix F) or for any image folder, with COLMAP.

Dataset mode (``irs-pose-recovery`` is the installed command; ``python pipelines/irs_pose_recovery.py`` and
``python -m pipelines.irs_pose_recovery`` run the same)::

    irs-pose-recovery DATASET_ROOT --out DIR [--workers N]

Every folder under DATASET_ROOT holding ``l_<n>.png`` (with ``r_<n>.png`` and ``d_<n>.exr``) is one scene
variant. Each is reconstructed from its left images with the intrinsics fixed (IRS: fx = fy = 480,
cx, cy = 480, 270 at 960x540), scaled to metres with z = 48 / d from the disparity EXRs (d in pixels at the
960-px IRS width), and filtered (>= 150 registered frames, mean reprojection error <= 1.5 px, scale-ratio
IQR <= 25% of the median). Writes ``DIR/<variant>/poses.json`` (c2w of left and right cameras, OpenCV axes
x right / y down / z forward, metres; right = left Trans(0.1 m, 0, 0)), ``DIR/<variant>/report.json`` and
``DIR/summary.json``, and prints a summary table. Variants whose report.json exists are skipped.

Folder mode (no metric scale without depth)::

    irs-pose-recovery recover --images DIR --intrinsics fx,fy,cx,cy --out poses.json

writes ``{"frames": [{"image": name, "c2w": 4x4}], "registered": n, "mean_reprojection_error": e}``
(c2w OpenCV, in COLMAP's arbitrary units; e in pixels). Images are taken in natural name order
(frame_2 before frame_10), which sequential matching relies on. The poses file gets a manifest beside it
(``.written-by.<name>``) and ``--work-dir`` one inside: a rerun replaces what an earlier ``recover`` wrote there;
a file it did not write, or one changed since, is refused before COLMAP runs
(``scenesplat_stereo.common.ownership``).

Exit status (``scenesplat_stereo.common.commandline``): 0 done, 2 bad arguments or input (one line naming the flag or
file), 130 interrupted, 1 internal error; ``recover`` exits 1 when no image registers.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

from pipelines.irs import (IRS_CAMERA, IRS_FOCAL_BASELINE, MAX_MEAN_REPROJECTION_ERROR, MAX_SCALE_IQR_FRACTION,
                           MIN_REGISTERED_FRAMES, Filters, VariantConfig, find_variants, run_dataset,
                           summary_table)
from scenesplat_stereo.captured.colmap import (EXHAUSTIVE_MAX_FRAMES, MATCHING_MODES, PinholeCamera, RecoveryOptions,
                                               image_size, recover_poses, recovery_json)
from scenesplat_stereo.common.commandline import Parser, run_command
from scenesplat_stereo.common.ownership import OwnedFile, OwnedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import argtype, parse_size, positive_number, whole_number

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
PROG = "irs-pose-recovery"  # the installed command (pyproject.toml [project.scripts])
OWNER = PROG  # recorded in OUT's manifest: a later run may resume or replace what it wrote there
RECOVER_OWNER = f"{PROG} recover"  # recorded beside recover's --out and in its --work-dir


def _colmap_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--matching", choices=MATCHING_MODES, default="auto",
                   help="feature matching: auto = exhaustive up to --exhaustive-max-frames frames, else "
                        "sequential (default auto)")
    p.add_argument("--exhaustive-max-frames", type=whole_number("--exhaustive-max-frames"), default=EXHAUSTIVE_MAX_FRAMES,
                   help="largest sequence matched exhaustively under --matching auto "
                        f"(default {EXHAUSTIVE_MAX_FRAMES})")
    p.add_argument("--vocab-tree", type=Path, default=None,
                   help="local COLMAP vocabulary-tree file: enables loop detection in sequential matching "
                        "(none is downloaded; without it there is no loop detection)")
    p.add_argument("--max-features", type=whole_number("--max-features"), default=8192, help="SIFT features per image (default 8192)")
    p.add_argument("--init-min-inliers", type=whole_number("--init-min-inliers"), default=100,
                   help="inliers required of COLMAP's initial image pair (default 100; lower for small images)")
    p.add_argument("--threads", type=int, default=-1, help="COLMAP threads (default: all cores, shared by workers)")
    p.add_argument("--seed", type=int, default=0, help="COLMAP random seed (default 0)")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's log")


def _options(args: argparse.Namespace) -> RecoveryOptions:
    return RecoveryOptions(matching=args.matching, exhaustive_max_frames=args.exhaustive_max_frames,
                           vocab_tree_path=args.vocab_tree, max_num_features=args.max_features,
                           init_min_num_inliers=args.init_min_inliers, num_threads=args.threads, seed=args.seed,
                           verbose=args.verbose)


def dataset_parser() -> argparse.ArgumentParser:
    p = Parser(prog=PROG, description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", type=Path, metavar="DATASET_ROOT", help="IRS dataset root (searched recursively)")
    p.add_argument("--out", type=Path, required=True, help="output folder (one sub-folder per variant)")
    p.add_argument("--workers", type=whole_number("--workers"), default=1, help="variants processed in parallel (processes; default 1)")
    p.add_argument("--image-size", type=argtype(parse_size, "--image-size"), default=None, metavar="WxH",
                   help="expected image size when the images are a resized copy of IRS (default 960x540); the "
                        "intrinsics are scaled from 960x540, the disparity stays in 960-px pixels")
    p.add_argument("--focal-baseline", type=positive_number("--focal-baseline"), default=IRS_FOCAL_BASELINE,
                   help=f"fx * B in pixels * metres for z = fx B / d (default {IRS_FOCAL_BASELINE:g})")
    p.add_argument("--min-registered", type=whole_number("--min-registered"), default=MIN_REGISTERED_FRAMES,
                   help=f"filter: registered frames at least (default {MIN_REGISTERED_FRAMES})")
    p.add_argument("--max-reprojection-error", type=positive_number("--max-reprojection-error"), default=MAX_MEAN_REPROJECTION_ERROR,
                   help=f"filter: mean reprojection error at most, pixels (default {MAX_MEAN_REPROJECTION_ERROR:g})")
    p.add_argument("--max-scale-iqr", type=positive_number("--max-scale-iqr"), default=MAX_SCALE_IQR_FRACTION,
                   help=f"filter: scale-ratio IQR / median at most (default {MAX_SCALE_IQR_FRACTION:g})")
    p.add_argument("--keep-colmap", action="store_true", help="keep each variant's COLMAP database and models")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _colmap_arguments(p)
    p.set_defaults(func=run_dataset_cli)
    return p


def recover_parser() -> argparse.ArgumentParser:
    p = Parser(prog=f"{PROG} recover",
               description="Recover camera poses (c2w, OpenCV axes, arbitrary units) of the "
                           "images of one folder seen by one fixed pinhole camera.")
    p.add_argument("--images", type=Path, required=True, help="folder of images (natural name order)")
    p.add_argument("--intrinsics", required=True, help="fx,fy,cx,cy in pixels (pixel centres at +0.5)")
    p.add_argument("--out", type=Path, required=True, help="output poses.json (a file an earlier recover wrote is "
                   "replaced, any other refused)")
    p.add_argument("--work-dir", type=Path, default=None, help="COLMAP work folder to keep (default: a temp one; new, "
                   "empty, or an earlier recover's)")
    _colmap_arguments(p)
    p.set_defaults(func=run_recover)
    return p


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def run_recover(args: argparse.Namespace) -> int:
    images = sorted((p for p in args.images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
                    key=lambda p: _natural_key(p.name)) if args.images.is_dir() else []
    if not images:
        raise ValueError(f"--images {args.images}: no images ({', '.join(IMAGE_SUFFIXES)})")
    camera = PinholeCamera.parse(args.intrinsics, *image_size(images[0]))
    check_apart(args.out, "--out", {"--images": args.images, "--work-dir": args.work_dir})
    out = OwnedFile(args.out, "--out", RECOVER_OWNER)  # before COLMAP runs
    if args.work_dir is not None:
        check_apart(args.work_dir, "--work-dir", {"--images": args.images})
        work = check_replaceable(args.work_dir, "--work-dir", RECOVER_OWNER)  # COLMAP's database is removed there
    with OwnedFolder(work, RECOVER_OWNER) if args.work_dir is not None else \
            tempfile.TemporaryDirectory(prefix="colmap-") as folder:
        recovery = recover_poses(images, camera, Path(folder), _options(args))
    out.write(json.dumps(recovery_json(recovery, [p.name for p in images]), indent=1) + "\n")
    print(f"{recovery.registered}/{len(images)} images registered, mean reprojection error "
          f"{recovery.mean_reprojection_error:.3f} px ({recovery.matching} matching) -> {args.out}")
    return 0 if recovery.registered else 1


def run_dataset_cli(args: argparse.Namespace) -> int:
    camera = IRS_CAMERA
    if args.image_size is not None:
        camera = IRS_CAMERA.scaled(*args.image_size)
    if not find_variants(args.root):  # nothing to do is not a success: the user expected poses
        raise ValueError(f"DATASET_ROOT {args.root}: no IRS variant (no folder holding l_<n>.png images); give the "
                         f"folder of the IRS download")
    out = check_replaceable(args.out, "--out", OWNER)
    check_apart(out, "--out", {"ROOT": args.root}, replaced=True)
    cfg = VariantConfig(out=out, camera=camera, focal_baseline=args.focal_baseline,
                        filters=Filters(args.min_registered, args.max_reprojection_error, args.max_scale_iqr),
                        options=_options(args), keep_colmap=args.keep_colmap)
    with OwnedFolder(out, OWNER):  # what it holds is recorded as this command's, however it ends (a rerun resumes)
        reports = run_dataset(args.root, cfg, workers=args.workers, progress=not args.no_progress)
    print(summary_table(reports))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``irs-pose-recovery``: the dataset mode, or ``recover`` as the first word; errors as every command's."""
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    if argv and argv[0] == "recover":
        return run_command(recover_parser(), argv[1:])
    return run_command(dataset_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
