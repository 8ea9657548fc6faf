"""``OUT/benchmark.json``: how a test set is measured (its one reader and writer).

The paper measures its two test sets differently (section 5, appendix C): ReplicaGS, rendered from 3DGS
teachers, "within a valid mask marking target regions supported by the teacher rendering (rendered alpha
>= 0.5)"; StereoNVS, captured with a stereo camera, over the full image (every pixel is real, so its
masks are all valid). The folder says which, so that ``sgmodel eval``'s Table 2 picks the right numbers
without a flag:

    {"masked": bool, "source": "rendered" | "captured", "protocol": "<one line for reports>"}

``scenesplat-stereo build --split-mode test`` writes ``masked: true`` (rendered); ``scenesplat-stereo
import stereonvs`` writes ``masked: false`` (captured). A folder without the file (a train/val build) has
no declared protocol: the table then uses full-image metrics and says so.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from scenesplat_stereo.common.files import atomic_write_json

BENCHMARK_NAME = "benchmark.json"
SOURCES = ("rendered", "captured")


class BenchmarkError(ValueError):
    """A ``benchmark.json`` that cannot be read; the message names the file and field."""


@dataclass(frozen=True)
class Benchmark:
    """How a test set is measured: ``masked`` (metrics over valid-mask pixels) or full image, where its
    images come from (``source``), and a one-line description of its sampling (``protocol``)."""

    masked: bool
    source: str
    protocol: str

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise BenchmarkError(f"benchmark source must be one of {SOURCES}, got {self.source!r}")


def write_benchmark(root: Path, benchmark: Benchmark) -> Path:
    """Write ``root/benchmark.json`` atomically."""
    return atomic_write_json(Path(root) / BENCHMARK_NAME, asdict(benchmark))


def read_benchmark(root: Path) -> Benchmark | None:
    """``root/benchmark.json``, or None when the folder has none; BenchmarkError when it is malformed."""
    path = Path(root) / BENCHMARK_NAME
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise BenchmarkError(f"{path}: unreadable ({e})") from None
    if not isinstance(doc, dict):
        raise BenchmarkError(f"{path}: expected a JSON object")
    for name, kind in (("masked", bool), ("source", str), ("protocol", str)):
        if not isinstance(doc.get(name), kind):
            raise BenchmarkError(f"{path}: field {name!r}: expected a {kind.__name__}, got {doc.get(name)!r}")
    try:
        return Benchmark(doc["masked"], doc["source"], doc["protocol"])
    except BenchmarkError as e:
        raise BenchmarkError(f"{path}: field 'source': {e}") from None
