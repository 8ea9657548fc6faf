"""PlayCanvas SOG ("spatially ordered Gaussians"): reader (versions 1 and 2, bundled or not) and writer (version 2,
bundled), numpy and OpenImageIO's WebP codec.

Written from the format as PlayCanvas' splat-transform 3.7.0 reads and writes it (``readSog`` / ``writeSog``).
A SOG is a ``meta.json`` and lossless WebP images, either side by side in a folder or bundled in one zip file
(``.sog``; members stored, ``meta.json`` among them). Texel i (row-major, from the top-left) of every
per-Gaussian image belongs to Gaussian i; images are at least ``count`` texels (the writer's size is
W = 4 ceil(sqrt(N) / 4), H = 4 ceil(N / W / 4)). Channels are 8-bit RGBA with *unassociated* alpha (an image
without alpha reads as A = 255).

* ``means``: ``means_l.webp`` and ``means_u.webp`` hold the low and high bytes of a 16-bit q per axis (RGB);
  t = min + (max - min) q / 65535 (``max - min`` taken as 1 when 0), position = sign(t) (e^|t| - 1), i.e. the
  inverse of t = sign(x) ln(|x| + 1). ``mins``/``maxs`` are 3 numbers.
* ``quats``: "smallest three": A = 252 + i where i is the index of the largest |component| of the wxyz
  quaternion (made positive), RGB the other three in wxyz order as p / 255 * 2 - 1 = sqrt(2) c; the largest is
  sqrt(1 - sum c^2). An A outside 252..255 is refused (splat-transform reads it as the identity).
* version 2 (``"version": 2``, ``count``): ``scales.webp`` RGB index ``scales.codebook`` (256 natural-log
  scales); ``sh0.webp`` RGB index ``sh0.codebook`` (256 values of the SH DC coefficient f_dc, not SH_C0-scaled)
  and A = round(255 opacity); read as opacity = clip(A / 255, 1e-6, 1 - 1e-6) as splat-transform does.
* version 1 (no ``version``; count = ``means.shape[0]``): scales RGB lerp ``scales.mins``..``maxs`` (3 each);
  sh0 RGBA lerp ``sh0.mins``..``maxs`` (4 each), the fourth being the opacity's logit.
* ``shN`` (optional; SH degree = ``bands``, 1..3, C = 3, 8, 15 coefficients above the DC term): a palette of
  ``count`` centroids in ``shN_centroids.webp`` (64 centroids a row, C texels each: centroid j's coefficient
  k at column (j mod 64) C + k, row j div 64, RGB the three colours) and ``shN_labels.webp`` (label = R + 256 G
  per Gaussian). v2: a centroid byte indexes ``shN.codebook`` (256); v1: bands from the centroid image's width
  (192, 512, 960), byte b -> mins + (maxs - mins) b / 255 (scalars), palette = (width div C) x height. A label
  beyond the palette reads as zero SH, as in splat-transform.

The writer (``save_sog``) writes version 2 as splat-transform does: Morton order, 16-bit positions, 256-entry
codebooks for log-scales and colours (density-weighted 1-D k-means over all values), and for SH a k-means palette of
min(64 Ki, 2^floor(log2(N / 1024)) Ki) centroids, capped at ``SH_PALETTE_MAX``, with a 256-entry codebook of
their values. It rounds to nearest where splat-transform truncates. OpenImageIO writes lossless WebP exactly,
except that libwebp drops the colour of texels whose alpha is 0: a Gaussian whose opacity byte is 0 (opacity
< 1/510, invisible) reads back with another colour. Errors of a round trip: docs/formats.md.
"""

from __future__ import annotations

import io
import json
import math
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.scene.compressed_ply import morton_order
from scenesplat_stereo.scene.gaussians import GaussianScene, decoded_scene

#: Coefficients above the DC term per SH degree (bands).
SH_COEFFS = (0, 3, 8, 15)
#: Version 1's centroid image widths, by bands.
V1_CENTROID_WIDTHS = {192: 1, 512: 2, 960: 3}
#: Largest SH palette ``save_sog`` builds (splat-transform goes to 65536; k-means here runs on the CPU or GPU).
SH_PALETTE_MAX = 4096
#: Opacity clamp of splat-transform's reader (its logit is clamped to logit(1e-6)).
OPACITY_EPS = 1e-6
WEBP_MAX_SIDE = 16383


class SogError(ValueError):
    """A SOG that cannot be read (or a scene that cannot be written); names the file and the field."""


# ------------------------------------------------------------------------------------------------ images
def read_webp(path: Path, source: str) -> tuple[np.ndarray, int, int]:
    """(uint8 RGBA [H*W, 4] row-major, W, H) of a WebP file, alpha unassociated (A = 255 without alpha)."""
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # else OpenImageIO premultiplies RGB by A
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None or inp.format_name() != "webp":
        if inp is not None:
            inp.close()
        raise SogError(f"{source}: not a readable WebP image ({oiio.geterror() or 'another format'})")
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
    inp.close()
    if pixels is None or spec.nchannels not in (3, 4):
        raise SogError(f"{source}: WebP image unreadable or with {spec.nchannels} channels (3 or 4 expected)")
    rgba = np.full((spec.width * spec.height, 4), 255, np.uint8)
    rgba[:, :spec.nchannels] = pixels.reshape(-1, spec.nchannels)
    return rgba, spec.width, spec.height


def write_webp(rgba: np.ndarray, width: int, height: int) -> bytes:
    """Lossless WebP bytes of uint8 RGBA texels [width * height, 4] (fewer are padded with zeros)."""
    import OpenImageIO as oiio

    img = np.zeros((height * width, 4), np.uint8)
    img[:len(rgba)] = rgba
    spec = oiio.ImageSpec(width, height, 4, "uint8")
    spec.attribute("compression", "lossless")
    spec.attribute("oiio:UnassociatedAlpha", 1)
    with tempfile.TemporaryDirectory(prefix="sog-") as tmp:
        name = os.path.join(tmp, "image.webp")
        out = oiio.ImageOutput.create(name)
        if out is None or not out.open(name, spec) or not out.write_image(img.reshape(height, width, 4)):
            raise SogError(f"OpenImageIO cannot write WebP: {oiio.geterror()}")
        out.close()
        return Path(name).read_bytes()


# ----------------------------------------------------------------------------------------------- reading
class SogSource:
    """A SOG's ``meta.json`` (parsed) and its images, from a ``.sog`` zip or a folder; ``name`` for messages."""

    def __init__(self, path: str | os.PathLike):
        path = Path(path)
        if path.is_dir():
            path = path / "meta.json"
        self.path, self._zip = path, None
        try:
            if path.name.endswith(".json") or not zipfile.is_zipfile(path):
                if path.suffix == ".sog":
                    raise SogError(f"{path}: not a zip file, or a truncated one (a .sog bundles meta.json and WebP "
                                   "images in a zip)")
                raw, self.name = path.read_bytes(), str(path)
            else:
                self._zip = zipfile.ZipFile(path)
                self.name = str(path)
                if "meta.json" not in self._zip.namelist():
                    raise SogError(f"{path}: no meta.json in the zip (members: "
                                   f"{', '.join(self._zip.namelist()[:8]) or 'none'})")
                raw = self._zip.read("meta.json")
        except OSError as e:
            raise SogError(f"{path}: cannot read ({e.strerror or e})") from None
        except zipfile.BadZipFile as e:
            raise SogError(f"{path}: corrupt zip ({e})") from None
        try:
            self.meta = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise SogError(f"{self.name}: meta.json: not JSON ({e})") from None
        if not isinstance(self.meta, dict):
            raise SogError(f"{self.name}: meta.json: expected a JSON object")

    def image(self, field: str, index: int) -> tuple[np.ndarray, int, int]:
        """The decoded image ``meta[field].files[index]``."""
        files = self.field(field, "files", None)
        if not isinstance(files, list) or len(files) <= index or not isinstance(files[index], str):
            raise SogError(f"{self.name}: meta.json {field}.files: expected at least {index + 1} file names")
        name, where = files[index], f"{self.name}: {field}.files[{index}] {files[index]!r}"
        with tempfile.TemporaryDirectory(prefix="sog-") as tmp:
            try:
                if self._zip is not None:
                    local = Path(tmp) / "image.webp"
                    local.write_bytes(self._zip.read(name))
                else:
                    local = self.path.parent / name
                    if not local.is_file():
                        raise KeyError(name)
            except KeyError:
                raise SogError(f"{where}: no such image") from None
            except (zipfile.BadZipFile, OSError) as e:
                raise SogError(f"{where}: cannot read ({e})") from None
            return read_webp(local, where)

    def field(self, key: str, sub: str | None, length: int | None = None, what: str = "numbers") -> object:
        """``meta[key][sub]`` (or ``meta[key]``); with ``length``, a float64 array of that many finite numbers
        (``length=0``: any length)."""
        value = self.meta.get(key)
        if sub is not None:
            value = value.get(sub) if isinstance(value, dict) else None
        if length is None:
            return value
        label = f"{key}.{sub}" if sub else key
        try:
            arr = np.array(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise SogError(f"{self.name}: meta.json {label}: expected {what}, got {str(value)[:60]}") from None
        if isinstance(value, (bool, str)) or value is None or (length and arr.size != length):
            raise SogError(f"{self.name}: meta.json {label}: expected {length or 'a list of'} {what}, got "
                           f"{str(value)[:60]}")
        if not np.isfinite(arr).all():
            raise SogError(f"{self.name}: meta.json {label}: non-finite value")
        return arr

    def count(self) -> int:
        """Gaussians: v2 ``count``, v1 ``means.shape[0]``."""
        version = self.meta.get("version")
        if version not in (None, 2):
            raise SogError(f"{self.name}: meta.json version: {version!r} is not supported (1 or 2)")
        value = self.meta.get("count") if version == 2 else (self.field("means", "shape") or [None])[0]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SogError(f"{self.name}: meta.json {'count' if version == 2 else 'means.shape'}: expected a "
                           f"positive whole number of Gaussians, got {value!r}")
        return value

    def sh_degree(self) -> int:
        """SH degree from meta.json (v1 without a ``shN`` entry: 0; v1 with one: read from its image)."""
        if "shN" not in self.meta:
            return 0
        if self.meta.get("version") == 2:
            bands = self.field("shN", "bands")
            if bands not in (1, 2, 3):
                raise SogError(f"{self.name}: meta.json shN.bands: expected 1, 2 or 3, got {bands!r}")
            return bands
        return V1_CENTROID_WIDTHS.get(self.image("shN", 0)[1], 0)

    def texels(self, field: str, index: int, n: int) -> np.ndarray:
        rgba, w, h = self.image(field, index)
        if w * h < n:
            raise SogError(f"{self.name}: {field}.files[{index}]: {w}x{h} texels, fewer than the {n} Gaussians")
        return rgba[:n]


def decode_sog(src: SogSource) -> tuple[np.ndarray, ...]:
    """(means, wxyz quats, log-scales, opacities, sh [N, K, 3], SH degree), float64, of a SOG (module docstring)."""
    n, v2 = src.count(), src.meta.get("version") == 2
    lo, hi = src.texels("means", 0, n), src.texels("means", 1, n)
    mins, maxs = src.field("means", "mins", 3), src.field("means", "maxs", 3)
    q = lo[:, :3].astype(np.float64) + 256.0 * hi[:, :3]
    t = mins + np.where(maxs - mins == 0, 1.0, maxs - mins) * (q / 65535.0)
    with np.errstate(over="ignore"):
        means = np.sign(t) * np.expm1(np.abs(t))
    quats = _unpack_quats(src.texels("quats", 0, n), src.name)
    s, c = src.texels("scales", 0, n), src.texels("sh0", 0, n)
    if v2:
        log_scales = src.field("scales", "codebook", 256, "256 codebook numbers")[s[:, :3]]
        dc = src.field("sh0", "codebook", 256, "256 codebook numbers")[c[:, :3]]
        opacities = np.clip(c[:, 3] / 255.0, OPACITY_EPS, 1.0 - OPACITY_EPS)
    else:
        smin, smax = src.field("scales", "mins", 3), src.field("scales", "maxs", 3)
        cmin, cmax = src.field("sh0", "mins", 4), src.field("sh0", "maxs", 4)
        log_scales = smin + (smax - smin) * (s[:, :3] / 255.0)
        lerp = cmin + (cmax - cmin) * (c / 255.0)
        dc, opacities = lerp[:, :3], 1.0 / (1.0 + np.exp(-lerp[:, 3]))
    degree = src.sh_degree()
    sh = np.zeros((n, (degree + 1) ** 2, 3))
    sh[:, 0] = dc
    if degree:
        sh[:, 1:] = _decode_shn(src, n, degree, v2)
    return means, quats, log_scales, opacities, sh, degree


def _unpack_quats(texels: np.ndarray, name: str) -> np.ndarray:
    tag = texels[:, 3].astype(np.int64) - 252
    if ((tag < 0) | (tag > 3)).any():
        bad = np.flatnonzero((tag < 0) | (tag > 3))
        raise SogError(f"{name}: quats.webp: {len(bad)} Gaussians have alpha {int(texels[bad[0], 3])} (Gaussian "
                       f"{int(bad[0])}), not 252..255 (the index of the largest component)")
    small = (texels[:, :3] / 255.0 * 2.0 - 1.0) / math.sqrt(2.0)
    quats = np.empty((len(texels), 4))
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[tag]  # [N, 3] slots of the three
    np.put_along_axis(quats, others, small, axis=1)
    np.put_along_axis(quats, tag[:, None], np.sqrt(np.maximum(0.0, 1.0 - (small**2).sum(1)))[:, None], axis=1)
    return quats


def _decode_shn(src: SogSource, n: int, degree: int, v2: bool) -> np.ndarray:
    """[N, C, 3] SH coefficients above the DC term (module docstring)."""
    coeffs = SH_COEFFS[degree]
    cen, cw, ch = src.image("shN", 0)
    labels = src.texels("shN", 1, n)
    label = labels[:, 0].astype(np.int64) + 256 * labels[:, 1].astype(np.int64)
    if v2:
        palette = src.field("shN", "count")
        if cw != 64 * coeffs or isinstance(palette, bool) or not isinstance(palette, int) \
                or not 0 < palette <= 64 * ch:
            raise SogError(f"{src.name}: shN: centroid image {cw}x{ch} does not hold shN.count {palette!r} "
                           f"centroids of {coeffs} texels (64 a row)")
        values = src.field("shN", "codebook", 256, "256 codebook numbers")[cen[:, :3]]
    else:
        palette = (cw // coeffs) * ch
        lo_, hi_ = (float(src.field("shN", k, 1)[0]) for k in ("mins", "maxs"))
        values = lo_ + (hi_ - lo_) * (cen[:, :3] / 255.0)
    values = values.reshape(ch, cw, 3)[:, :64 * coeffs].reshape(ch * 64, coeffs, 3)
    inside = label < palette
    out = np.zeros((n, coeffs, 3))
    out[inside] = values[label[inside]]
    return out


def load_sog(path: str | os.PathLike) -> GaussianScene:
    """Read a SOG (a ``.sog`` zip, a ``meta.json`` or a folder holding one) into a ``GaussianScene``.
    ``SogError`` naming the file and field when it is broken."""
    src = SogSource(path)
    return decoded_scene(src.name, SogError, *decode_sog(src))


# ----------------------------------------------------------------------------------------------- writing
def _codebook(values: np.ndarray, k: int = 256, alpha: float = 0.2, bins: int = 1 << 14,
              iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """A 1-D codebook of ``values``: (k ascending float32 entries, uint8 nearest-entry labels shaped like values).

    Density-weighted k-means, as splat-transform's ``quantize1d`` (which takes alpha 0.5 and an exact dynamic
    programme): the values are binned into a ``bins``-bin histogram over their range, each bin weighs
    count^alpha (so sparse tails get entries that plain k-means would give the dense middle), and Lloyd's
    iterations start from weighted quantiles. alpha 0.2 gave the smallest RMS and largest errors of 0.5, 0.3,
    0.2, 0.1 on the guitar's log-scales and colours."""
    flat = values.reshape(-1).astype(np.float64)
    lo, hi = float(flat.min()), float(flat.max())
    if hi - lo < 1e-20:
        return np.full(k, lo, np.float32), np.zeros(values.shape, np.uint8)
    counts, edges = np.histogram(flat, bins, (lo, hi))
    x = 0.5 * (edges[1:] + edges[:-1])[counts > 0]
    w = counts[counts > 0].astype(np.float64) ** alpha
    cw, cwx = np.concatenate([[0.0], np.cumsum(w)]), np.concatenate([[0.0], np.cumsum(w * x)])
    centres = np.unique(np.interp((np.arange(k) + 0.5) / k * cw[-1], cw[1:], x))
    for _ in range(iterations):
        cut = np.searchsorted(x, 0.5 * (centres[1:] + centres[:-1]))
        start, end = np.concatenate([[0], cut]), np.concatenate([cut, [len(x)]])
        weight = cw[end] - cw[start]
        centres = np.unique(np.where(weight > 0, (cwx[end] - cwx[start]) / np.where(weight > 0, weight, 1), centres))
    centres = np.concatenate([centres, np.full(k - len(centres), centres[-1])]).astype(np.float32)
    labels = np.searchsorted(0.5 * (centres[1:].astype(np.float64) + centres[:-1]), values)
    return centres, np.minimum(labels, k - 1).astype(np.uint8)


def _kmeans(x: np.ndarray, k: int, iterations: int = 10, fit_rows: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """k-means of rows x [N, D] (torch; CUDA when there): (centroids [k, D] float32, labels [N] int64 of every
    row's nearest centroid). Lloyd's iterations run on a random ``fit_rows`` k of the rows (all when fewer),
    starting from k of them."""
    import torch

    dev = "cuda" if torch.cuda.is_available() else "cpu"
    X = torch.from_numpy(np.ascontiguousarray(x, np.float32)).to(dev)
    rows = torch.randperm(len(X), generator=torch.Generator().manual_seed(0)).to(dev)
    fit = X[rows[:fit_rows * k]]
    C = fit[:k].clone()

    def assign(points: torch.Tensor) -> torch.Tensor:
        c2 = (C * C).sum(1)
        step = max(1, (1 << 22) // k)  # rows a block: a [step, k] distance block of 16 MiB
        return torch.cat([(c2[None] - 2.0 * points[i:i + step] @ C.T).argmin(1)
                          for i in range(0, len(points), step)])

    for _ in range(iterations):
        labels = assign(fit)
        count = torch.zeros(k, device=dev).index_add_(0, labels, torch.ones(len(fit), device=dev))
        total = torch.zeros_like(C).index_add_(0, labels, fit)
        C = torch.where(count[:, None] > 0, total / count.clamp(min=1)[:, None], C)
    return C.cpu().numpy(), assign(X).cpu().numpy()


def _pack_quats(quats: np.ndarray) -> np.ndarray:
    q = quats.astype(np.float64) / np.linalg.norm(quats, axis=1, keepdims=True)
    largest = np.abs(q).argmax(1)
    q *= np.where(np.take_along_axis(q, largest[:, None], 1) < 0, -1.0, 1.0) * math.sqrt(2.0)
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    out = np.empty((len(q), 4), np.uint8)
    out[:, :3] = np.clip(np.rint(255.0 * (np.take_along_axis(q, others, 1) * 0.5 + 0.5)), 0, 255)
    out[:, 3] = 252 + largest
    return out


def encode_sog(scene: GaussianScene, path: str | os.PathLike = "<memory>",
               sh_palette_max: int = SH_PALETTE_MAX) -> bytes:
    """The bundled ``.sog`` (zip) bytes of ``scene`` (module docstring)."""
    n = len(scene)
    if n == 0:
        raise SogError(f"{path}: an empty scene has no SOG (images of at least one texel)")
    width = math.ceil(math.sqrt(n) / 4) * 4
    height = math.ceil(n / width / 4) * 4
    if max(width, height) > WEBP_MAX_SIDE:
        raise SogError(f"{path}: {n} Gaussians need {width}x{height} texels, beyond WebP's {WEBP_MAX_SIDE}")
    order = morton_order(scene.means)
    s = scene.subset(order)
    files: dict[str, bytes] = {}

    def image(name: str, texels: np.ndarray) -> None:  # one texel a Gaussian, in Morton order
        files[name] = write_webp(texels, width, height)

    t = np.sign(s.means.astype(np.float64)) * np.log1p(np.abs(s.means.astype(np.float64)))
    mins, maxs = t.min(0), t.max(0)
    q = np.rint(65535.0 * (t - mins) / np.where(maxs > mins, maxs - mins, 1.0)).astype(np.uint16)
    alpha = np.full((n, 1), 255, np.uint8)
    image("means_l.webp", np.hstack([(q & 255).astype(np.uint8), alpha]))
    image("means_u.webp", np.hstack([(q >> 8).astype(np.uint8), alpha]))
    image("quats.webp", _pack_quats(s.quats))
    scale_book, scale_labels = _codebook(np.log(s.scales.astype(np.float64)))
    image("scales.webp", np.hstack([scale_labels, alpha]))
    colour_book, colour_labels = _codebook(s.sh[:, 0].astype(np.float64))
    opacity = np.clip(np.rint(s.opacities.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    image("sh0.webp", np.hstack([colour_labels, opacity[:, None]]))
    meta = {"version": 2, "asset": {"generator": "scenesplat_stereo.scene.sog"}, "count": n,
            "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": colour_book.tolist(), "files": ["sh0.webp"]}}
    if s.sh_degree:
        coeffs = SH_COEFFS[s.sh_degree]
        palette = min(64, 2 ** math.floor(math.log2(n / 1024))) * 1024 if n >= 1024 else n
        palette = max(1, min(palette, sh_palette_max, n))
        rest = s.sh[:, 1:].transpose(0, 2, 1).reshape(n, 3 * coeffs)  # channel-major, as f_rest
        centroids, labels = _kmeans(rest, palette)
        book, cells = _codebook(centroids)
        cells = cells.reshape(palette, 3, coeffs).transpose(0, 2, 1).reshape(-1, 3)  # [palette * C, RGB]
        rows = math.ceil(palette / 64)
        px = np.zeros((rows * 64 * coeffs, 4), np.uint8)
        px[:len(cells), :3], px[:, 3] = cells, 255
        files["shN_centroids.webp"] = write_webp(px, 64 * coeffs, rows)
        image("shN_labels.webp", np.stack([labels & 255, labels >> 8, 0 * labels, 255 + 0 * labels], 1)
              .astype(np.uint8))
        meta["shN"] = {"count": palette, "bands": s.sh_degree, "codebook": book.tolist(),
                       "files": ["shN_centroids.webp", "shN_labels.webp"]}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for name, data in files.items():
            z.writestr(zipfile.ZipInfo(name, (1980, 1, 1, 0, 0, 0)), data)
        z.writestr(zipfile.ZipInfo("meta.json", (1980, 1, 1, 0, 0, 0)), json.dumps(meta))
    return buf.getvalue()


def save_sog(scene: GaussianScene, path: str | os.PathLike, durable: bool = True) -> Path:
    """Write ``scene`` as a bundled version-2 ``.sog``, atomically. Returns the path."""
    path = Path(path)
    atomic_write_bytes(path, encode_sog(scene, path), durable=durable)
    return path
