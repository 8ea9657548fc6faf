"""Synthetic PlayCanvas SOG files for the tests, written straight from the format description (meta.json and
lossless WebP images through OpenImageIO; nothing of ``scenesplat_stereo.scene.sog``), and their float64 decode.

``make_sog`` draws random texels and codebooks, writes them as a folder (``meta.json`` + images) or a bundled
``.sog`` zip, and returns what it wrote; ``reference_decode`` decodes that, Gaussian by Gaussian, into
(means, wxyz quats, log-scales, opacities, sh [N, K, 3]) as the format description says (docs in
``scenesplat_stereo/scene/sog.py``)."""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

COEFFS = {1: 3, 2: 8, 3: 15}


def write_webp(path: Path, rgba: np.ndarray) -> None:
    """Lossless WebP of uint8 [H, W, 4], alpha unassociated (every alpha > 0: libwebp keeps such texels)."""
    spec = oiio.ImageSpec(rgba.shape[1], rgba.shape[0], 4, "uint8")
    spec.attribute("compression", "lossless")
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(rgba)), oiio.geterror()
    out.close()


def make_sog(out: Path, n: int, degree: int, version: int = 2, bundle: bool = False, seed: int = 0,
             palette: int = 70) -> dict:
    """Write a random SOG of n Gaussians; returns {"meta", "images" (name -> [H, W, 4]), "path"}."""
    rng = np.random.default_rng(seed)
    w = math.ceil(math.sqrt(n) / 4) * 4
    h = math.ceil(n / w / 4) * 4
    tex = lambda: rng.integers(1, 256, (h, w, 4), dtype=np.uint8)  # noqa: E731  (alpha >= 1)
    quats = tex()
    quats[..., 3] = rng.integers(252, 256, (h, w))
    images = {"means_l.webp": tex(), "means_u.webp": tex(), "quats.webp": quats, "scales.webp": tex(),
              "sh0.webp": tex()}
    mins = rng.uniform(-2, 0, 3)
    meta: dict = {"means": {"mins": mins.tolist(), "maxs": (mins + rng.uniform(0.5, 2, 3)).tolist(),
                            "files": ["means_l.webp", "means_u.webp"]},
                  "quats": {"files": ["quats.webp"]}}
    if version == 2:
        meta.update(version=2, count=n,
                    scales={"codebook": np.sort(rng.uniform(-8, 0, 256)).tolist(), "files": ["scales.webp"]},
                    sh0={"codebook": np.sort(rng.uniform(-2, 2, 256)).tolist(), "files": ["sh0.webp"]})
    else:
        meta["means"]["shape"] = [n, 3]
        meta.update(scales={"mins": [-8, -7, -6], "maxs": [-1, 0, 0.5], "files": ["scales.webp"]},
                    sh0={"mins": [-2, -1.5, -1, -5], "maxs": [2, 1.5, 1, 5], "files": ["sh0.webp"]})
    if degree:
        c = COEFFS[degree]
        rows = math.ceil(palette / 64)
        images["shN_centroids.webp"] = rng.integers(1, 256, (rows, 64 * c, 4), dtype=np.uint8)
        labels = rng.integers(0, palette + 5, (h, w))  # a few labels beyond the palette: zero SH
        images["shN_labels.webp"] = np.stack([labels % 256, labels // 256, 0 * labels, 255 + 0 * labels],
                                             -1).astype(np.uint8)
        meta["shN"] = {"files": ["shN_centroids.webp", "shN_labels.webp"]}
        if version == 2:
            meta["shN"].update(count=palette, bands=degree, codebook=np.sort(rng.uniform(-1, 1, 256)).tolist())
        else:
            meta["shN"].update(mins=-0.8, maxs=0.9)
    out.mkdir(parents=True, exist_ok=True)
    for name, rgba in images.items():
        write_webp(out / name, rgba)
    (out / "meta.json").write_text(json.dumps(meta))
    path = out
    if bundle:
        path = out.with_suffix(".sog")
        with zipfile.ZipFile(path, "w") as z:
            for name in [*images, "meta.json"]:
                z.write(out / name, name)
    return {"meta": meta, "images": images, "path": path, "n": n, "degree": degree, "version": version}


def reference_decode(sog: dict) -> tuple[np.ndarray, ...]:
    """float64 decode of ``make_sog``'s output, one Gaussian at a time."""
    meta, img, n, degree = sog["meta"], sog["images"], sog["n"], sog["degree"]
    flat = {k: v.reshape(-1, 4).astype(np.int64) for k, v in img.items()}
    k = (degree + 1) ** 2
    means, quats, log_scales, opacities, sh = (np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3)), np.zeros(n),
                                               np.zeros((n, k, 3)))
    for i in range(n):
        for a in range(3):
            q = flat["means_l.webp"][i, a] + 256 * flat["means_u.webp"][i, a]
            lo, hi = meta["means"]["mins"][a], meta["means"]["maxs"][a]
            t = lo + (hi - lo) * q / 65535
            means[i, a] = math.copysign(math.exp(abs(t)) - 1, t)
        r, g, b, tag = flat["quats.webp"][i]
        largest = tag - 252
        small = [(v / 255 * 2 - 1) / math.sqrt(2) for v in (r, g, b)]
        slots = [j for j in range(4) if j != largest]
        for j, v in zip(slots, small):
            quats[i, j] = v
        quats[i, largest] = math.sqrt(max(0.0, 1 - sum(v * v for v in small)))
        s, c = flat["scales.webp"][i], flat["sh0.webp"][i]
        if sog["version"] == 2:
            log_scales[i] = [meta["scales"]["codebook"][s[a]] for a in range(3)]
            sh[i, 0] = [meta["sh0"]["codebook"][c[a]] for a in range(3)]
            opacities[i] = min(max(c[3] / 255, 1e-6), 1 - 1e-6)
        else:
            lo, hi = meta["scales"]["mins"], meta["scales"]["maxs"]
            log_scales[i] = [lo[a] + (hi[a] - lo[a]) * s[a] / 255 for a in range(3)]
            lo, hi = meta["sh0"]["mins"], meta["sh0"]["maxs"]
            v = [lo[a] + (hi[a] - lo[a]) * c[a] / 255 for a in range(4)]
            sh[i, 0], opacities[i] = v[:3], 1 / (1 + math.exp(-v[3]))
        if degree:
            cc = COEFFS[degree]
            label = flat["shN_labels.webp"][i, 0] + 256 * flat["shN_labels.webp"][i, 1]
            cen = img["shN_centroids.webp"]
            palette = meta["shN"]["count"] if sog["version"] == 2 else (cen.shape[1] // cc) * cen.shape[0]
            if label < palette:
                for j in range(cc):
                    texel = cen[label // 64, (label % 64) * cc + j, :3]
                    for ch in range(3):
                        if sog["version"] == 2:
                            sh[i, 1 + j, ch] = meta["shN"]["codebook"][texel[ch]]
                        else:
                            lo, hi = meta["shN"]["mins"], meta["shN"]["maxs"]
                            sh[i, 1 + j, ch] = lo + (hi - lo) * texel[ch] / 255
    return means, quats, log_scales, opacities, sh
