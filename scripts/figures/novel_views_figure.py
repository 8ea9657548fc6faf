"""Novel views of one real stereo pair, side by side for several predictions of it (docs/model_card.md):

    python scripts/figures/novel_views_figure.py OUT.png LEFT.png "naive-GS=PRED1" "StereoGaussians=PRED2" \
        [--views left,right,up,forward] [--width 320]

Each PRED is an ``sgmodel predict`` output folder (its ``views/<name>.png`` are renders from the same cameras
for every method); the first row is the left input, then one row per method, labelled.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from scenesplat_stereo.common.files import atomic_write_bytes


def tile(path: Path, width: int) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise SystemExit(f"novel_views_figure: {path}: not a readable image")
    return cv2.resize(image, (width, round(image.shape[0] * width / image.shape[1])), interpolation=cv2.INTER_AREA)


def labelled(row: list[np.ndarray], text: str) -> np.ndarray:
    strip = np.full((22, sum(t.shape[1] for t in row) + 4 * (len(row) - 1), 3), 255, np.uint8)
    cv2.putText(strip, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    gap = np.full((row[0].shape[0], 4, 3), 255, np.uint8)
    body = np.concatenate([x for t in row for x in (t, gap)][:-1], axis=1)
    return np.concatenate([strip, body], axis=0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("left", type=Path)
    p.add_argument("methods", nargs="+", help="LABEL=PREDICT_FOLDER")
    p.add_argument("--views", default="left,right,up,forward")
    p.add_argument("--width", type=int, default=300)
    args = p.parse_args()
    views = args.views.split(",")
    rows = [labelled([tile(args.left, args.width)], "left input")]
    for spec in args.methods:
        label, _, folder = spec.partition("=")
        rows.append(labelled([tile(Path(folder) / "views" / f"{v}.png", args.width) for v in views],
                             f"{label}: views {', '.join(views)}"))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 6), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    ok, png = cv2.imencode(".png", np.concatenate(rows, axis=0))
    atomic_write_bytes(args.out, png.tobytes())
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
