"""What both command lines (``scenesplat-stereo``, ``sgmodel``) share about parsing what users type.

``Parser`` is ``argparse.ArgumentParser`` with prefix matching off (``allow_abbrev=False``): a mistyped or
shortened flag is refused instead of silently landing on another (``--rig`` is not ``--right``). Sub-command
parsers made through ``add_subparsers`` inherit the class, so every level refuses abbreviations.
"""

from __future__ import annotations

import argparse


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` that never takes an abbreviation of a long flag for the flag."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
