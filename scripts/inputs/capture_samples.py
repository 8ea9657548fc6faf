"""Write tests/data/captures/<capture>.npz: splat-transform's decode of a few Gaussians of each real capture in
../shared/data/captures, against which tests/scenesplat_stereo/scene/test_sog.py and tests/scenesplat_stereo/scene/test_splat.py check our readers.

Each capture is converted to an INRIA .ply by PlayCanvas splat-transform 3.7.0 (the npm package pinned in
scripts/checks/viewer/package.json; `cd scripts/checks/viewer && npm ci` first):

    node scripts/checks/viewer/node_modules/@playcanvas/splat-transform/bin/cli.mjs -w CAPTURE OUT.ply

and the float32 values of rows ``sample_rows(N)`` (the first 8 and 56 more drawn with seed 0) of that file are
kept, as the file stores them: ``rows`` [64], ``count`` (N), ``xyz`` [64, 3], ``rot`` [64, 4] (rot_0..3, wxyz
as written), ``scale`` [64, 3] (natural logs), ``opacity`` [64] (logit), ``f_dc`` [64, 3], ``f_rest`` [64, R]
(channel-major, R = 0, 24 or 45). The captures themselves are never copied into the repository.

With ``--streamed DIR`` (a streamed SOG folder, e.g. playcanvas/engine's examples/assets/splats/playbot), also
``<name>-lod<L>.npz`` for levels 0 and 3, converted with ``-L <L>`` (splat-transform's level selection).

    python scripts/inputs/capture_samples.py [--captures ../shared/data/captures] [--out tests/data/captures] \
        [--streamed /work/streamed-scenes/playbot]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
CLI = ROOT / "scripts" / "checks" / "viewer" / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"
sys.path.insert(0, str(ROOT))

from scenesplat_stereo.scene.ply import columns, read_elements, read_ply_header  # noqa: E402


def sample_rows(n: int) -> np.ndarray:
    """The rows kept of a capture of n Gaussians: 0..7 and 56 others drawn without replacement (seed 0)."""
    rest = np.random.default_rng(0).choice(np.arange(8, n), size=56, replace=False)
    return np.concatenate([np.arange(8), np.sort(rest)])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--captures", type=Path, default=ROOT.parent / "shared" / "data" / "captures")
    p.add_argument("--out", type=Path, default=ROOT / "tests" / "data" / "captures")
    p.add_argument("--streamed", type=Path, default=None, help="a streamed SOG folder (lod-meta.json)")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(f, f.parent.name, []) for f in sorted(args.captures.glob("*/*")) if f.suffix in (".sog", ".splat")]
    if args.streamed:
        jobs += [(args.streamed / "lod-meta.json", f"{args.streamed.name}-lod{level}", ["-L", str(level)])
                 for level in (0, 3)]
    for capture, name, flags in jobs:
        with tempfile.TemporaryDirectory() as tmp:
            ply = Path(tmp) / "decoded.ply"
            subprocess.run(["node", str(CLI), "-w", *flags, str(capture), str(ply)], check=True,
                           capture_output=True)
            header = read_ply_header(ply)
            v = read_elements(header, {"vertex"})["vertex"]
        rows = sample_rows(len(v))
        rest = sorted((n for n in v.dtype.names if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
        get = lambda names: columns(ply, v[rows], "vertex", names).astype(np.float32)  # noqa: E731
        np.savez_compressed(args.out / f"{name}.npz", rows=rows, count=len(v),
                            xyz=get(["x", "y", "z"]), rot=get([f"rot_{i}" for i in range(4)]),
                            scale=get([f"scale_{i}" for i in range(3)]), opacity=get(["opacity"])[:, 0],
                            f_dc=get([f"f_dc_{i}" for i in range(3)]),
                            f_rest=get(rest) if rest else np.zeros((len(rows), 0), np.float32))
        print(f"{name}: {len(v)} Gaussians, {len(rest)} f_rest", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
