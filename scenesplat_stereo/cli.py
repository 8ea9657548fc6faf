"""``scenesplat-stereo`` command line: parse, call, print. Each command's work lives in its room.

Commands: ``render`` (a teacher to PNG images), ``build``, ``inspect``, ``demo-teachers``,
``bench render``, ``bench build``. Units and conventions are stated in each command's ``--help``.
"""

from __future__ import annotations

import argparse
import sys


def _add_render(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo import render_cmd

    p = sub.add_parser(
        "render",
        help="render a teacher .ply to PNG images along an orbit or a trajectory",
        description=render_cmd.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    render_cmd.add_arguments(p)
    p.set_defaults(func=render_cmd.run)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    from scenesplat_stereo.bench import render as bench_render

    p = sub.add_parser("bench", help="benchmarks: what accuracy costs in time (markdown tables)")
    benches = p.add_subparsers(dest="bench", required=True)
    r = benches.add_parser("render", help="rasteriser speed/accuracy knobs, against gsplat and the float64 "
                           "reference", description=bench_render.__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    bench_render.add_arguments(r)
    r.set_defaults(func=bench_render.run)


# Each entry adds one sub-command. Kept as a list so that each room registers its own command here
# in one line, and the parser stays thin.
_COMMANDS = [_add_render, _add_bench]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
