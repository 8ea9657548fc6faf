"""The paper's Table 2 (zero-shot comparison): ``sgmodel eval`` over several benchmarks and methods at once.

    sgmodel eval --split test --data StereoNVS=data/stereonvs --data ReplicaGS=data/replicags \\
        --checkpoint run/checkpoints/best.pt --method forward-splat --method naive-gs --out table2/

Every (benchmark, method) pair is one ``sgmodel eval`` run with its own report in
``OUT/<benchmark>/<method>/`` (metrics.json, targets.csv, scenes.md, sheet.png). ``OUT/table2.md`` and
``OUT/table2.json`` hold the table: one row per method in the paper's order (the baselines without
learned prediction, forward-splat then naive-GS, then the model), per benchmark PSNR, SSIM and LPIPS
(means over all targets; a benchmark whose targets carry group labels, such as ``import multiview``'s
"between" and "beside", gets a column per group after its own), the best value of each column in bold.

Which numbers: a benchmark folder's ``benchmark.json`` (scenesplat_stereo.shards.benchmark_file) says whether it is
measured over the valid masks (rendered test sets such as ReplicaGS: ``psnr_masked`` and so on, as the
paper does) or over the full image (captured ones such as StereoNVS); a folder without one (a train/val
build) is measured over the full image, and the notes say so. Without the VGG16 ImageNet weights LPIPS is
not computed: its cells read "n/a" and the notes say why.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

from scenesplat_stereo.common.commandline import Interrupted
from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.common.ownership import OwnedFolder, check_apart, check_replaceable
from scenesplat_stereo.common.text import key_safe_name, markdown_table, value_cell
from scenesplat_stereo.shards.benchmark_file import read_benchmark
from sgmodel.data.loader import read_split
from sgmodel.evaluation.evaluate import OWNER, eval_inputs, evaluate, method_of

TABLE_MD, TABLE_JSON = "table2.md", "table2.json"
#: Row order and labels of the paper's Table 2 ("Stereo geometry without learned prediction", then ours).
ROWS = (("forward-splat", "forward-splat"), ("naive-gs", "naive-GS"), ("checkpoint", "StereoGaussians"))
BASELINE_GROUP = "*Stereo geometry without learned prediction*"
COLUMNS = (("psnr", "PSNR ↑", 3, max), ("ssim", "SSIM ↑", 4, max), ("lpips", "LPIPS ↓", 4, min))


@dataclass(frozen=True)
class Column:
    """One benchmark of the table: its name, folder, and whether it is measured over the valid masks
    (``masked``), with the reason (``region``: what benchmark.json says, or that there is none)."""

    name: str
    data: Path
    masked: bool
    region: str


@dataclass(frozen=True)
class Row:
    """One method of the table: ``method`` ("checkpoint", "naive-gs", "forward-splat"), its label, encoder, size,
    the per-benchmark means (``metrics.json``'s ``mean``) keyed by column name, and its precision."""

    method: str
    label: str
    encoder: str
    resolution: int
    means: dict[str, dict]
    precision: str = "float32"


def columns(data: list[tuple[str, Path]], split: str) -> list[Column]:
    """The benchmarks of ``--data``, checked before anything runs: unique names usable as folder names,
    the split present (DataError), a readable benchmark.json (BenchmarkError) or none."""
    out, seen = [], set()
    for name, path in data:
        if key_safe_name(name) != name or name in seen:
            raise ValueError(f"--data {name}={path}: the name must be unique and without '.', '/', blanks or '__' "
                             "(it names a report folder); give NAME=PATH")
        seen.add(name)
        read_split(path, split)
        bench = read_benchmark(path)
        if bench is None:
            out.append(Column(name, Path(path), False, "full image (no benchmark.json)"))
        else:
            what = "valid-mask pixels" if bench.masked else "full image"
            out.append(Column(name, Path(path), bench.masked, f"{what} ({bench.source}: {bench.protocol})"))
    return out


def cell(means: dict, metric: str, masked: bool) -> float | None:
    """One number of a row's means: ``<metric>_masked`` over valid masks, else ``<metric>``; None when it
    was not computed (LPIPS without weights) or undefined (NaN: no target had a valid pixel)."""
    value = means.get(f"{metric}_masked" if masked else metric)
    return None if value is None or math.isnan(value) else value


def table_markdown(cols: list[Column], rows: list[Row]) -> str:
    """The table: a header per benchmark and metric, the baselines' group line, one row per method; the
    best value of each column in bold, "n/a" where a metric was not computed."""
    header = ["Method"] + [f"{c.name} {label}" for c in cols for _, label, _, _ in COLUMNS]
    values = {(r.method, c.name, m): cell(r.means[c.name], m, c.masked) for r in rows for c in cols
              for m, _, _, _ in COLUMNS}
    best = {}
    for c in cols:
        for m, _, _, pick in COLUMNS:
            got = [v for r in rows if (v := values[(r.method, c.name, m)]) is not None]
            best[(c.name, m)] = pick(got) if len(got) > 1 else None
    body = []
    if any(r.method != "checkpoint" for r in rows):
        body.append([BASELINE_GROUP] + [""] * (len(header) - 1))
    for r in rows:
        line = [f"**{r.label}**" if r.method == "checkpoint" else r.label]
        for c in cols:
            for m, _, digits, _ in COLUMNS:
                v = values[(r.method, c.name, m)]
                text = value_cell(v, digits)
                line.append(f"**{text}**" if v is not None and v == best[(c.name, m)] else text)
        body.append(line)
    return markdown_table(header, body)


def notes(cols: list[Column], rows: list[Row], split: str, targets: dict[str, int], lpips: str,
          left_out: dict[str, int] | None = None) -> str:
    """What each column measures, how many targets (and how many of them, ``left_out``, have no valid pixel and
    are left out of its masked means), each method's encoder and size, and what was not computed."""
    left_out = left_out or {}
    lines = [f"- {c.name}: `{c.data}`, split {split}, {targets[c.name]} targets"
             f"{f' ({left_out[c.name]} without a valid pixel)' if left_out.get(c.name) else ''}; {c.region}"
             for c in cols]
    lines += [f"- {r.label}: encoder {r.encoder}, {r.resolution}x{r.resolution}, {r.precision}" for r in rows]
    if not lpips.startswith("LPIPS"):
        lines.append(f"- LPIPS {lpips}: give `--lpips-vgg` (torchvision's vgg16-397923af.pth)")
    return "\n".join(lines)


def run_table(args: argparse.Namespace, methods: list[str], device: str) -> int:
    """Evaluate every method on every ``--data`` folder, write the reports and the table, print it. OUT and
    each report folder in it (replaced as a whole) are checked before anything runs."""
    cols = columns(args.data, args.split)
    check_apart(args.out, "--out", eval_inputs(args))
    check_replaceable(args.out, "--out", OWNER)  # its tables and reports of earlier runs, nothing of anyone else
    for c in cols:
        for m in methods:
            check_replaceable(Path(args.out) / c.name / m, "--out", OWNER)
    labels = dict(ROWS)
    order = [m for m, _ in ROWS if m in methods]
    built = {m: method_of(m, args, device) for m in order}  # every checkpoint and encoder loads before any run
    with OwnedFolder(args.out, OWNER):  # every file in OUT recorded as eval's, however it ends
        rows, targets, left_out, lpips, shown, done = [], {}, {}, "", {c.name: c for c in cols}, []
        for m in order:
            means = {}
            for c in cols:
                try:
                    result = evaluate(built[m], c.data, args.split, Path(args.out) / c.name / m, device,
                                      args.lpips_vgg, args.batch_size, not args.no_progress)
                except KeyboardInterrupt:
                    raise Interrupted(f"{len(done)} of {len(cols) * len(order)} reports finished and kept in "
                                      f"{args.out} ({', '.join(done) or 'none'}), the table not written; rerun the "
                                      f"same command") from None
                done.append(f"{c.name}/{m}")
                means[c.name], targets[c.name], lpips = result["mean"], result["targets"], result["lpips"]
                left_out[c.name] = max(left_out.get(c.name, 0), result["targets_without_valid_pixels"])
                for g, group_mean in result.get("groups", {}).items():  # a column per target group after its benchmark's
                    name = f"{c.name} {g}"
                    shown.setdefault(name, dataclasses.replace(c, name=name))
                    means[name], targets[name] = group_mean, result["group_targets"][g]
            rows.append(Row(m, labels[m], built[m].encoder, built[m].resolution, means, built[m].precision))
        cols = sorted(shown.values(), key=lambda c: [k.name for k in cols].index(c.name.split(" ")[0]))
        text = table_markdown(cols, rows) + "\n\n" + notes(cols, rows, args.split, targets, lpips, left_out) + "\n"
        doc = {"split": args.split, "lpips": lpips,
               "benchmarks": [{"name": c.name, "data": str(c.data.resolve()), "masked": c.masked, "region": c.region,
                               "targets": targets[c.name]} for c in cols],
               "rows": [{"method": r.method, "label": r.label, "encoder": r.encoder, "resolution": r.resolution,
                         "precision": r.precision,
                         "cells": {c.name: {m: cell(r.means[c.name], m, c.masked) for m, _, _, _ in COLUMNS}
                                   for c in cols}} for r in rows]}
        atomic_write_bytes(Path(args.out) / TABLE_MD, text.encode())
        atomic_write_bytes(Path(args.out) / TABLE_JSON, (json.dumps(doc, indent=2) + "\n").encode())
    print(text)
    print(f"reports in {args.out}/<benchmark>/<method>/; table in {Path(args.out) / TABLE_MD}")
    return 0
