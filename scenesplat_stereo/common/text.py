"""Text the user types or reads: ``WxH`` image sizes, names that become sample keys, fixed-width tables.

One parser, one sanitiser and one table layout for every command (``build``, ``render``, ``demo-teachers``,
``bench``, the IRS pipelines), so the same input is accepted or refused the same way everywhere.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Sequence

_SIZE_RE = re.compile(r"\s*(\d+)\s*[xX]\s*(\d+)\s*")
_KEY_UNSAFE = re.compile(r"[.\s/\\]+")  # WebDataset splits member names at the first '.'; no paths or blanks


def parse_size(text: str, what: str = "size") -> tuple[int, int]:
    """``"616x456"`` -> (616, 456): width and height in pixels, both >= 1. ValueError naming ``what``
    (e.g. ``--resolution``) otherwise."""
    m = _SIZE_RE.fullmatch(str(text))
    if m is None:
        raise ValueError(f"{what} {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 616x456")
    w, h = int(m.group(1)), int(m.group(2))
    if w < 1 or h < 1:
        raise ValueError(f"{what} {text!r}: width and height must be >= 1 pixel")
    return w, h


def argtype(parse: Callable[[str, str], object], flag: str) -> Callable[[str], object]:
    """An argparse ``type`` from ``parse(text, flag)`` that raises ValueError: argparse shows the message
    (which names ``flag``) and the command exits 2."""
    def convert(text: str):
        try:
            return parse(text, flag)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    return convert


def parse_number(text: str, flag: str, kind: type = int, low: float | None = None, strict: bool = False,
                 high: float | None = None, strict_high: bool = False):
    """``kind(text)`` (int or float, finite), at least ``low`` (above it when ``strict``) and at most ``high``
    (below it when ``strict_high``); ValueError naming ``flag`` otherwise."""
    try:
        value = kind(text)
    except ValueError:
        raise ValueError(f"{flag} {text!r}: expected {'a whole number' if kind is int else 'a number'}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ValueError(f"{flag} {text!r}: expected a finite number")
    if low is not None and (value <= low if strict else value < low):
        raise ValueError(f"{flag} {value}: must be {'>' if strict else '>='} {low}")
    if high is not None and (value >= high if strict_high else value > high):
        raise ValueError(f"{flag} {value}: must be {'<' if strict_high else '<='} {high}")
    return value


def whole_number(flag: str, low: int = 1, high: int | None = None) -> Callable[[str], int]:
    """An argparse ``type`` for a whole number >= ``low`` (and <= ``high``)."""
    return argtype(lambda t, f: parse_number(t, f, int, low, high=high), flag)


def positive_number(flag: str) -> Callable[[str], float]:
    """An argparse ``type`` for a finite number > 0."""
    return argtype(lambda t, f: parse_number(t, f, float, 0.0, strict=True), flag)


def non_negative_number(flag: str) -> Callable[[str], float]:
    """An argparse ``type`` for a finite number >= 0."""
    return argtype(lambda t, f: parse_number(t, f, float, 0.0), flag)


def open_fraction(flag: str) -> Callable[[str], float]:
    """An argparse ``type`` for a number strictly between 0 and 1."""
    return argtype(lambda t, f: parse_number(t, f, float, 0.0, strict=True, high=1.0, strict_high=True), flag)


def parse_sizes(text: str, what: str = "sizes") -> list[tuple[int, int]]:
    """Comma-separated ``WxH`` sizes (at least one)."""
    sizes = [parse_size(s, what) for s in str(text).split(",") if s.strip()]
    if not sizes:
        raise ValueError(f"{what} {text!r}: expected one or more WIDTHxHEIGHT, comma-separated")
    return sizes


def key_safe_name(name: str) -> str:
    """A scene or variant name usable in a sample key ``<name>__<frame>``: runs of '.', '/', '\\' and
    whitespace become '_', runs of '_' collapse to one (``__`` separates name and frame), and leading or
    trailing '_' are dropped. ValueError when nothing is left."""
    safe = re.sub(r"_{2,}", "_", _KEY_UNSAFE.sub("_", str(name))).strip("_")
    if not safe:
        raise ValueError(f"name {name!r}: nothing usable in a sample key is left")
    return safe


def format_table(rows: Sequence[Sequence[str]], align: str = "", rule: bool = False, free_last: bool = False
                 ) -> str:
    """Fixed-width text table. ``align`` gives 'l' or 'r' per column (default: first left, others right);
    ``rule`` puts a dashed line under the header row; ``free_last`` leaves the last column unpadded (free
    text such as reasons). Trailing blanks are stripped."""
    rows = [[str(c) for c in r] for r in rows]
    n = max(len(r) for r in rows)
    rows = [r + [""] * (n - len(r)) for r in rows]
    align = align or "l" + "r" * (n - 1)
    widths = [max(len(r[i]) for r in rows) for i in range(n)]
    if free_last:
        widths[-1] = 0
    lines = ["  ".join(c.rjust(w) if align[i] == "r" else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths)))
             .rstrip() for r in rows]
    if rule:
        lines.insert(1, "-" * max(len(line) for line in lines))
    return "\n".join(lines)


def value_cell(value: float | None, digits: int) -> str:
    """A table cell of a measured value with ``digits`` decimals; "n/a" for None (not computed, or undefined:
    a mean over no target)."""
    return "n/a" if value is None else f"{value:.{digits}f}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured markdown table (for docs/ and reports): one header row, a rule, the rows."""
    lines = ["| " + " | ".join(str(c) for c in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def parse_counts(text: str, flag: str) -> dict[str, int] | int:
    """``'A=3,B=0'`` -> {"A": 3, "B": 0}, or one integer >= 0 for every name (e.g. ``--val-scenes``)."""
    try:
        if "=" not in text:
            return parse_number(text, flag, int, 0)
        return {k.strip(): parse_number(v, f"{flag} {k.strip()}", int, 0)
                for k, v in (item.split("=") for item in text.split(",") if item.strip())}
    except ValueError as e:
        raise ValueError(f"{flag} {text!r}: expected 'Subset=k,...' or one integer >= 0 ({e})") from None


def parse_number_or_none(text: str, flag: str) -> float | None:
    """A float, or None for ``'none'`` (e.g. ``--min-psnr``)."""
    return None if text.strip().lower() == "none" else parse_number(text, flag, float)
