"""``scenesplat-stereo`` command line: parse, call, print. Each command's work lives in its room.

Commands: ``render`` (a teacher to PNG images), ``build``, ``import stereonvs``, ``inspect``,
``demo-teachers``, ``bench render``, ``bench build``, ``bench encode``. Units and conventions are stated in each
command's ``--help``. Exit status (``scenesplat_stereo.commandline``): 0 done, 2 bad arguments or input (one line
naming the flag or file), 130 interrupted, 1 internal error (traceback with ``--debug``); ``build`` exits 3 when
a teacher failed, ``inspect`` 1 when a check failed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenesplat_stereo.commandline import Parser, run_command
from scenesplat_stereo.text import argtype, parse_size, whole_number


def _add_render(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo import render_cmd

    p = sub.add_parser(
        "render",
        help="render a teacher (folder or scene file) to PNG images along an orbit or a trajectory",
        description=render_cmd.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    render_cmd.add_arguments(p)
    p.set_defaults(func=render_cmd.run)


def _add_build(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo import build

    p = sub.add_parser("build", help="render teacher scenes into SceneSplat-Stereo shards (stereo pairs + targets)",
                       description=build.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    build.add_arguments(p)
    p.set_defaults(func=build.run)


def _add_import(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo import stereonvs

    p = sub.add_parser("import", help="turn a published benchmark into test shards (StereoNVS-Real)")
    sources = p.add_subparsers(dest="source", required=True)
    s = sources.add_parser("stereonvs", help="StereoNVS-Real (LLFF poses_bounds, left/right images) -> test shards",
                           description=stereonvs.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    stereonvs.add_arguments(s)
    s.set_defaults(func=stereonvs.run)


def _add_inspect(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo import inspection

    p = sub.add_parser("inspect", help="Table-6 counts, a contact sheet and integrity checks of a built dataset",
                       description=inspection.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    inspection.add_arguments(p)
    p.set_defaults(func=inspection.run)


def _add_demo_teachers(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo import demo

    p = sub.add_parser("demo-teachers", help="write procedural indoor teacher scenes (plain layout) to OUT",
                       description=demo.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="output folder; one sub-folder per scene")
    p.add_argument("--scenes", type=whole_number("--scenes"), default=4, help="number of scenes (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--gaussians", type=whole_number("--gaussians"), default=demo.DEFAULT_NUM_GAUSSIANS,
                   help=f"Gaussians per room (default {demo.DEFAULT_NUM_GAUSSIANS})")
    p.add_argument("--frames", type=whole_number("--frames"), default=12, help="trajectory frames per scene (default 12)")
    p.add_argument("--size", type=argtype(parse_size, "--size"), default="256x192", metavar="WxH",
                   help="native image size in pixels (default 256x192)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace) -> int:
        width, height = args.size
        folders = demo.write_demo_teachers(args.out, n_scenes=args.scenes, seed=args.seed,
                                           num_gaussians=args.gaussians, n_frames=args.frames, width=width,
                                           height=height, progress=not args.no_progress)
        print(f"wrote {len(folders)} demo teachers to {args.out}")
        return 0

    p.set_defaults(func=run)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo.bench import build as bench_build
    from scenesplat_stereo.bench import encode as bench_encode
    from scenesplat_stereo.bench import formats as bench_formats
    from scenesplat_stereo.bench import render as bench_render

    p = sub.add_parser("bench", help="benchmarks: what accuracy costs in time (markdown tables)")
    benches = p.add_subparsers(dest="bench", required=True)
    r = benches.add_parser("render", help="rasteriser speed/accuracy knobs, against gsplat and the float64 "
                           "reference", description=bench_render.__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    bench_render.add_arguments(r)
    r.set_defaults(func=bench_render.run)
    b = benches.add_parser("build", help="dataset build throughput: pairs/s, renders/s, time split, projections",
                           description=bench_build.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bench_build.add_arguments(b)
    b.set_defaults(func=bench_build.run)
    e = benches.add_parser("encode", help="host JPEG/PNG encoding: per-image cost, threads against processes (no GPU)",
                           description=bench_encode.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bench_encode.add_arguments(e)
    e.set_defaults(func=bench_encode.run)
    f = benches.add_parser("formats", help="scene file formats: real captures read, every writer's size, time and "
                           "error", description=bench_formats.__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    bench_formats.add_arguments(f)
    f.set_defaults(func=bench_formats.run)


# Each entry adds one sub-command. Kept as a list so that each room registers its own command here
# in one line, and the parser stays thin.
_COMMANDS = [_add_render, _add_build, _add_import, _add_inspect, _add_demo_teachers, _add_bench]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="scenesplat-stereo",
        description="SceneSplat-Stereo: calibrated stereo pairs and nearby target views rendered from "
        "3DGS teacher scenes. Cameras are OpenCV (x right, y down, z forward); poses on disk are "
        "camera-to-world in metres.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit status and its one-line errors are ``commandline.run_command``'s."""
    return run_command(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
