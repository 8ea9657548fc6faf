"""Depth a built dataset shows: percentiles of the left camera's rendered depth (metres), per subset.

``python scripts/figures/depth_percentiles.py DATASET [--split train]`` reads every sample's
``left_depth.exr`` (present when the dataset was built with ``--with-depth``) and its valid pixels (depth > 0,
finite; the expected depth is 0 where nothing was rendered), and prints a markdown table: pixels, the
5/25/50/75/95th percentiles, and the share of pixels nearer than 0.5, 1, 2 and 5 m, per subset (or per scene,
``--group scene``) and overall.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from scenesplat_stereo.shards import webdataset as shards
from scenesplat_stereo.shards.encode import decode_image

PERCENTILES = (5, 25, 50, 75, 95)
NEARER_THAN = (0.5, 1.0, 2.0, 5.0)  # metres


def depths_by_subset(dataset: Path, split: str, group: str = "subset") -> dict[str, np.ndarray]:
    """Subset (or scene, ``group="scene"``) -> every valid left-depth value (metres, float32) of the split;
    ValueError when the split has no depth maps."""
    found: dict[str, list[np.ndarray]] = defaultdict(list)
    for shard in sorted((dataset / split).glob("shard-*.tar")):
        for key, members in shards.iter_shard(shard):
            if "left_depth.exr" not in members:
                raise ValueError(f"{shard}: {key} has no left_depth.exr (build with --with-depth)")
            z = decode_image(members["left_depth.exr"], "exr").astype(np.float32).reshape(-1)
            found[json.loads(members["json"])[group]].append(z[np.isfinite(z) & (z > 0)])
    if not found:
        raise ValueError(f"{dataset / split}: no shards")
    return {s: np.concatenate(v) for s, v in sorted(found.items())}


def table(by_subset: dict[str, np.ndarray]) -> str:
    rows = ["| group | pixels | " + " | ".join(f"p{p} (m)" for p in PERCENTILES) + " | "
            + " | ".join(f"< {d:g} m" for d in NEARER_THAN) + " |",
            "|---" * (2 + len(PERCENTILES) + len(NEARER_THAN)) + "|"]
    groups = dict(by_subset)
    if len(groups) > 1:
        groups["all"] = np.concatenate(list(by_subset.values()))
    for name, z in groups.items():
        cells = [f"{v:.2f}" for v in np.percentile(z, PERCENTILES)] + [f"{(z < d).mean():.0%}" for d in NEARER_THAN]
        rows.append(f"| {name} | {len(z):,} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("--split", default="train")
    p.add_argument("--group", choices=("subset", "scene"), default="subset", help="one row per subset or per scene")
    args = p.parse_args()
    print(table(depths_by_subset(args.dataset, args.split, args.group)))


if __name__ == "__main__":
    main()
