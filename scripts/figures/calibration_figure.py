"""docs/images/rectification.png and the numbers of docs/calibration.md.

    python scripts/figures/calibration_figure.py [OUT.png]

On the raw rig pair of scripts/inputs/rig_pair.py (radtan lenses): top, the raw images with SIFT matches of the left
image and, in the right image, each one's epipolar curve (its ray from 0.3 m to 30 m, through the rig's
calibration and lens model: curves, not lines, because of the distortion); bottom, the pair after
``sgmodel.pairs.rectify``: the same matches on one image row (green lines). Then it prints the stereo check's
figures on that pair and on altered copies, and the time of the check and of the rectification at a larger
size for each ``max_side`` (the check's speed/accuracy knob), on this machine's CPU.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.shards.encode import decode_image, encode_png, to_uint8
from scripts.inputs.rig_pair import BASELINE, H, W, render, write_rig
from sgmodel.pairs.rectify import Rectification
from sgmodel.pairs.rig import FISHEYE, StereoRig, read_rig
from sgmodel.pairs.stereo_check import matches, measure

ZOOM = 2  # the figure shows every image at twice its size
N_POINTS = 10
COLOURS = [tuple(int(c) for c in cv2.applyColorMap(np.uint8([[i * 255 // (N_POINTS - 1)]]), cv2.COLORMAP_TURBO)[0, 0])
           for i in range(N_POINTS)]


def rectified_points(rig: StereoRig, rect: Rectification, points: np.ndarray, camera: int) -> np.ndarray:
    """Raw pixels [n,2] (OpenCV centres) of camera 0 or 1 -> pixels of the rectified image (OpenCV centres)."""
    K, D, R = (rig.K1, rig.D1, rect.R1) if camera == 0 else (rig.K2, rig.D2, rect.R2)
    P = rect.K.copy()
    P[:2, 2] -= 0.5
    undistort = cv2.fisheye.undistortPoints if rig.model == FISHEYE else cv2.undistortPoints
    return undistort(points.reshape(-1, 1, 2), K, D, R=R, P=P).reshape(-1, 2)


def epipolar_curve(rig: StereoRig, point: np.ndarray) -> np.ndarray:
    """Pixels [m,2] in the raw right image of the left pixel's ray from 0.3 m to 30 m."""
    undistort = cv2.fisheye.undistortPoints if rig.model == FISHEYE else cv2.undistortPoints
    x = undistort(point.reshape(1, 1, 2), rig.K1, rig.D1).reshape(2)
    depths = np.geomspace(0.3, 30.0, 200)
    pts = (np.array([x[0], x[1], 1.0])[None] * depths[:, None]) @ rig.R.T + rig.T
    if rig.model == FISHEYE:
        out = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), rig.K2, rig.D2)[0]
    else:
        out = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), rig.K2, rig.D2)[0]
    return out.reshape(-1, 2)


def _px(p) -> tuple[int, int]:
    """An OpenCV pixel position on the zoomed canvas, in 1/16 pixel steps (cv2's shift = 4)."""
    return tuple(int(round((c + 0.5) * ZOOM * 16 - 8)) for c in p)


def figure(folder: Path) -> tuple[np.ndarray, dict]:
    rig = read_rig(folder / "opencv.yml")
    raw = [decode_image((folder / f"{n}.png").read_bytes(), "png") for n in ("left", "right")]
    rect = Rectification.of(rig, (W, H))
    rectified = list(rect.rectify(*raw))
    p1, p2 = matches(*raw)
    order = np.argsort(p1[:, 0] + 3 * p1[:, 1])                   # spread over the image
    pick = order[np.linspace(0, len(order) - 1, N_POINTS).astype(int)]
    tiles = [cv2.resize(cv2.cvtColor(x, cv2.COLOR_RGB2BGR), None, fx=ZOOM, fy=ZOOM, interpolation=cv2.INTER_NEAREST)
             for x in raw + rectified]
    r1, r2 = rectified_points(rig, rect, p1[pick], 0), rectified_points(rig, rect, p2[pick], 1)
    for i, k in enumerate(pick):
        c = COLOURS[i]
        cv2.circle(tiles[0], _px(p1[k]), 5 * 16, c, 2, cv2.LINE_AA, 4)
        cv2.line(tiles[1], _px((-1, p1[k][1])), _px((W, p1[k][1])), (255, 255, 255), 1, cv2.LINE_AA, 4)
        cv2.polylines(tiles[1], [np.array([_px(q) for q in epipolar_curve(rig, p1[k])], np.int32)], False, c, 2,
                      cv2.LINE_AA, 4)
        cv2.circle(tiles[1], _px(p2[k]), 5 * 16, c, 2, cv2.LINE_AA, 4)
        for t, q in ((2, r1[i]), (3, r2[i])):
            cv2.line(tiles[t], _px((-1, r1[i][1])), _px((W, r1[i][1])), (255, 255, 255), 1, cv2.LINE_AA, 4)
            cv2.circle(tiles[t], _px(q), 5 * 16, c, 2, cv2.LINE_AA, 4)
    before, after = measure(*raw), measure(*rectified, rectified_here=True)
    labels = ["raw left: radtan lens, its own K and rotation",
              f"raw right: epipolar curves; white: the left rows (|dy| {before.dy_median:.1f} px median)",
              "rectified left (sgmodel.pairs.rectify): white lines = the points' rows",
              f"rectified right: on the left points' rows (|dy| {after.dy_median:.2f} px median)"]
    titled = []
    for tile, text in zip(tiles, labels):
        bar = np.full((30, tile.shape[1], 3), 255, np.uint8)
        cv2.putText(bar, text, (6, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        titled.append(np.concatenate([bar, tile], 0))
    gap = np.full((titled[0].shape[0], 8, 3), 255, np.uint8)
    rows = [np.concatenate([titled[0], gap, titled[1]], 1), np.concatenate([titled[2], gap, titled[3]], 1)]
    image = np.concatenate([rows[0], np.full((8, rows[0].shape[1], 3), 255, np.uint8), rows[1]], 0)
    return image[..., ::-1], {"raw": before, "rectified": after, "raw_images": raw, "rectified_images": rectified}


def _shift(image: np.ndarray, dy: float = 0.0, degrees: float = 0.0) -> np.ndarray:
    h, w = image.shape[:2]
    M = cv2.getRotationMatrix2D((w / 2 - 0.5, h / 2 - 0.5), degrees, 1.0)
    M[1, 2] += dy
    return cv2.warpAffine(image, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def check_table(out: dict, truth) -> None:
    right = truth.c2w_rect.copy()
    right[:3, 3] += BASELINE * right[:3, 0]
    K = np.array([[250.0, 0, W / 2], [0, 250.0, H / 2], [0, 0, 1]])
    rgb, _ = render(out["scene"], [truth.c2w_rect, right], [K, K], W, H)
    ideal = [to_uint8(x) for x in rgb]
    rl, rr = out["rectified_images"]
    cases = [("rendered rectified pair (ideal)", ideal, False),
             ("raw rig pair after our rectification", (rl, rr), True),
             ("raw rig pair, not rectified", out["raw_images"], False),
             ("ideal pair, left and right swapped", ideal[::-1], False),
             ("ideal pair, right image 3 px lower", (ideal[0], _shift(ideal[1], dy=3.0)), False),
             ("ideal pair, right image turned 1.5 deg", (ideal[0], _shift(ideal[1], degrees=1.5)), False)]
    print("| pair (320x240) | matches | median abs dy (px) | 95th pct abs dy (px) | negative disparity | verdict |")
    print("|---|---:|---:|---:|---:|---|")
    for name, (a, b), here in cases:
        c = measure(a, b, rectified_here=here)
        verdict = "ok" if not c.warnings else "warns: " + ("swapped" if "swapped" in c.warnings[0] else
                                                             "vertical disparity")
        print(f"| {name} | {c.matches} | {c.dy_median:.2f} | {c.dy_p95:.2f} | {c.negative_fraction:.0%} | {verdict} |")


def timing_table(scene, truth, rig: StereoRig, scale: int = 6) -> None:
    """The check at each max_side and the rectification, on a pair rendered at ``scale`` x 320x240."""
    w, h = W * scale, H * scale
    K = np.array([[250.0 * scale, 0, w / 2], [0, 250.0 * scale, h / 2], [0, 0, 1]])
    right = truth.c2w_rect.copy()
    right[:3, 3] += BASELINE * right[:3, 0]
    rgb, _ = render(scene, [truth.c2w_rect, right], [K, K], w, h)
    ideal = [to_uint8(x) for x in rgb]
    shifted = (ideal[0], _shift(ideal[1], dy=2.0 * scale))
    print(f"\n| max_side (pair {w}x{h}) | check (s) | matches | median abs dy, ideal (px) | 95th pct, ideal (px) | "
          f"measured shift of a {2 * scale} px shift (px) |")
    print("|---:|---:|---:|---:|---:|---:|")
    for max_side in (640, 960, 1280, 1920):
        t = time.perf_counter()
        c = measure(*ideal, max_side=max_side)
        seconds = time.perf_counter() - t
        s = measure(*shifted, max_side=max_side)
        print(f"| {max_side} | {seconds:.2f} | {c.matches} | {c.dy_median:.2f} | {c.dy_p95:.2f} | {s.dy_shift:.2f} |")
    big = StereoRig(rig.K1 * [[scale], [scale], [1]], rig.D1, rig.K2 * [[scale], [scale], [1]], rig.D2, rig.R, rig.T,
                    rig.model, (w, h), rig.source, rig.size_field)
    t = time.perf_counter()
    rect = Rectification.of(big, (w, h))
    t_maps = time.perf_counter() - t
    t = time.perf_counter()
    rect.rectify(*ideal)
    print(f"\nrectification at {w}x{h}: maps {t_maps:.3f} s (once per rig and size), remap of a pair "
          f"{time.perf_counter() - t:.3f} s")


def main() -> None:
    default = Path(__file__).resolve().parents[2] / "docs" / "images" / "rectification.png"
    out_png = Path(sys.argv[1]) if len(sys.argv) > 1 else default
    from scripts.inputs.rig_pair import room

    scene = room()
    with tempfile.TemporaryDirectory() as tmp:
        truth = write_rig(Path(tmp), "radtan", scene)
        image, out = figure(Path(tmp))
        rig = read_rig(Path(tmp) / "opencv.yml")
    atomic_write_bytes(out_png, encode_png(image))
    print(f"wrote {out_png}\n")
    check_table({**out, "scene": scene}, truth)
    timing_table(scene, truth, rig)


if __name__ == "__main__":
    main()
