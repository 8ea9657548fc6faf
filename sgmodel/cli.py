"""``sgmodel`` command line. The training and evaluation commands land with the model issues."""

from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="sgmodel",
        description="StereoGaussians model. No model command is available in this version: "
        "the dataset toolkit (scenesplat-stereo) and the differentiable rasteriser it trains "
        "through are. See docs/architecture.md for what comes next.",
    )
    parser.add_argument("--version", action="version", version="sgmodel 0.1.0")
    parser.parse_args(argv)
    parser.print_help()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
