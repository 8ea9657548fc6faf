"""``scenesplat-stereo`` command line: the table of commands. Each command's module (named in ``COMMANDS``) holds
its flags (``add_arguments``) and its work (``run``).

Commands: ``render`` (a teacher to PNG images), ``build``, ``import stereonvs``, ``import multiview``, ``inspect``,
``demo-teachers``, ``compose-teachers``, ``bench render``, ``bench build``, ``bench encode``, ``bench scenes``,
``bench formats``. Units and conventions are stated in each command's ``--help``. Exit status
(``scenesplat_stereo.common.commandline``): 0 done, 2 bad arguments or input (one line naming the flag or file),
130 interrupted, 1 internal error (traceback with ``--debug``); ``build`` exits 3 when a teacher failed,
``inspect`` 1 when a check failed.
"""

from __future__ import annotations

import argparse
import sys

from scenesplat_stereo.common.commandline import Command, Parser, add_commands, run_command

COMMANDS = (
    Command("render", "render a teacher (folder or scene file) to PNG images along an orbit or a trajectory",
            "scenesplat_stereo.build.render_teacher"),
    Command("build", "render teacher scenes into SceneSplat-Stereo shards (stereo pairs + targets)",
            "scenesplat_stereo.build.run"),
    Command("import", "turn a published benchmark into test shards (StereoNVS-Real, multi-view line sets)",
            dest="source", commands=(
                Command("stereonvs", "StereoNVS-Real (LLFF poses_bounds, left/right images) -> test shards",
                        "scenesplat_stereo.captured.stereonvs"),
                Command("multiview", "rectified views along one line (Middlebury 2001 nine-view sets) -> test shards",
                        "scenesplat_stereo.captured.multiview"))),
    Command("inspect", "Table-6 counts, a contact sheet and integrity checks of a built dataset",
            "scenesplat_stereo.build.inspection"),
    Command("demo-teachers", "write procedural indoor teacher scenes (plain layout) to OUT",
            "scenesplat_stereo.build.demo"),
    Command("compose-teachers", "real captures composed into procedural rooms at metric sizes (plain-layout teachers)",
            "scenesplat_stereo.build.compose"),
    Command("bench", "benchmarks: what accuracy costs in time (markdown tables)", dest="bench", commands=(
        Command("render", "rasteriser speed/accuracy knobs, against gsplat and the float64 reference",
                "scenesplat_stereo.bench.render"),
        Command("build", "dataset build throughput: pairs/s, renders/s, time split, projections",
                "scenesplat_stereo.bench.build"),
        Command("encode", "host JPEG/PNG encoding: per-image cost, threads against processes (no GPU)",
                "scenesplat_stereo.bench.encode"),
        Command("scenes", "every scene writer's time and file size at N Gaussians, SH degree 0 and 2",
                "scenesplat_stereo.bench.scenes"),
        Command("formats", "scene file formats: real captures read, every writer's size, time and error",
                "scenesplat_stereo.bench.formats"))),
)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="scenesplat-stereo",
        description="SceneSplat-Stereo: calibrated stereo pairs and nearby target views rendered from "
        "3DGS teacher scenes. Cameras are OpenCV (x right, y down, z forward); poses on disk are "
        "camera-to-world in metres.",
    )
    add_commands(parser, COMMANDS)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit status and its one-line errors are ``commandline.run_command``'s."""
    return run_command(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
