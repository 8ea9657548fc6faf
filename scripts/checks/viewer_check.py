"""Open an ``sgmodel predict`` output in a real viewer in headless Chromium (software WebGL) and take a
screenshot; compare it with the left image (PSNR over the pixels the scene covers in the left image).

* ``--viewer supersplat`` (default): the SuperSplat viewer with the scene (``scene.compressed.ply``,
  ``scene.ply`` or ``scene.sog``) and ``settings.json``, opened with ``?noui&noanim&webgl``;
* ``--viewer spark``: Spark (three.js; ``scripts/checks/viewer/spark.html``) with the scene (``scene.spz``,
  ``scene.ply``, ``scene.compressed.ply`` or ``scene.sog``) seen from the camera of ``cameras.json``.

Needs npm packages and Debian's Chromium (not part of the Python package):

    apt-get install -y chromium
    (cd scripts/checks/viewer && npm install)   # supersplat-viewer, spark, three, playwright-core, splat-transform

    python scripts/checks/viewer_check.py OUT --left LEFT.png --screenshot docs/images/supersplat.png

The page's files, the scene and its viewer file are put in a temporary folder, served on 127.0.0.1 and
opened in a window of the left image's aspect (``--scale`` times its size). Prints the PSNR; exits 1 when
the page did not render.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import cv2
import numpy as np

from scenesplat_stereo.common.measure import psnr_from_mse

VIEWER = Path(__file__).resolve().parent / "viewer"
PUBLIC = VIEWER / "node_modules" / "@playcanvas" / "supersplat-viewer" / "public"
#: Scene files each viewer opens, in order of preference, and the viewer file it needs.
SCENES = {"supersplat": (("scene.compressed.ply", "scene.ply", "scene.sog"), "settings.json"),
          "spark": (("scene.spz", "scene.ply", "scene.compressed.ply", "scene.sog"), "cameras.json")}


def serve(folder: Path) -> tuple[http.server.ThreadingHTTPServer, int]:
    """A static file server of ``folder`` on 127.0.0.1 (a free port), in a daemon thread."""
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    handler = functools.partial(Quiet, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, server.server_address[1]


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    err = ((a.astype(np.float64) - b.astype(np.float64)) / 255.0)[mask]
    return psnr_from_mse(max(float((err**2).mean()), 1e-12))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="an sgmodel predict output folder")
    p.add_argument("--left", type=Path, required=True, help="the left image the scene was predicted from")
    p.add_argument("--screenshot", type=Path, required=True, help="where to write the screenshot (PNG)")
    p.add_argument("--scale", type=float, default=2.0, help="window size = this x the left image's (default 2)")
    p.add_argument("--chromium", default="/usr/bin/chromium", help="Chromium executable")
    p.add_argument("--viewer", choices=sorted(SCENES), default="supersplat", help="which viewer (default supersplat)")
    args = p.parse_args()
    names, viewer_file = SCENES[args.viewer]
    scene = next((args.out / s for s in names if (args.out / s).is_file()), None)
    if scene is None or not (args.out / viewer_file).is_file():
        sys.exit(f"viewer_check: {args.out} has no {viewer_file} and {' or '.join(names)}")
    if not PUBLIC.is_dir():
        sys.exit(f"viewer_check: {PUBLIC} is missing: run `npm install` in {VIEWER}")
    left = cv2.imread(str(args.left), cv2.IMREAD_COLOR)
    h, w = left.shape[:2]
    W, H = round(w * args.scale), round(h * args.scale)
    with tempfile.TemporaryDirectory() as tmp:
        site = Path(tmp)
        if args.viewer == "supersplat":
            for f in ("index.html", "index.js", "index.css"):
                shutil.copy(PUBLIC / f, site / f)
            page = f"index.html?noui&noanim&webgl&content=./{scene.name}"
        else:
            shutil.copy(VIEWER / "spark.html", site / "spark.html")
            (site / "node_modules").symlink_to(VIEWER / "node_modules")
            page = f"spark.html?content=./{scene.name}&cameras=./cameras.json"
        shutil.copy(scene, site / scene.name)
        shutil.copy(args.out / viewer_file, site / viewer_file)
        server, port = serve(site)
        try:
            url = f"http://127.0.0.1:{port}/{page}"
            shot = site / "shot.png"
            command = ["node", str(VIEWER / "screenshot.mjs"), url, str(shot), str(W), str(H), args.chromium]
            run = subprocess.run(command, capture_output=True, text=True, timeout=600, check=False)
        finally:
            server.shutdown()
        if run.returncode or not shot.is_file():
            print(run.stdout, run.stderr, file=sys.stderr)
            return 1
        args.screenshot.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, args.screenshot)
    image = cv2.resize(cv2.imread(str(args.screenshot), cv2.IMREAD_COLOR), (w, h), interpolation=cv2.INTER_AREA)
    covered = left.max(axis=2) > 8  # the guitar pair's background is black: compare where the scene is
    print(f"{scene.name} in {args.viewer} at {W}x{H}: PSNR {psnr(image, left, covered):.2f} dB against "
          f"{args.left.name} over {int(covered.sum())} covered pixels (of {w * h}); screenshot {args.screenshot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
