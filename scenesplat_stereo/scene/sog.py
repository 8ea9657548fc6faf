"""PlayCanvas SOG ("spatially ordered Gaussians"): reader (versions 1 and 2, bundled or not; numpy) and writer
(version 2, bundled; torch, ``sog_texels``), and OpenImageIO's WebP codec.

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
their values (``palettes``). It rounds to nearest where splat-transform truncates. OpenImageIO writes lossless
WebP exactly, at libwebp's fastest method for the per-Gaussian images (``WEBP_METHOD``), except that libwebp
drops the colour of texels whose alpha is 0: a Gaussian whose opacity byte is 0 (opacity < 1/510, invisible)
reads back with another colour (which one depends on the method). The images are encoded side by side in
threads. Sizes, times and errors of a round trip: docs/formats.md.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import os
import struct
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.scene import row_tasks
from scenesplat_stereo.scene.compressed_ply import morton_order
from scenesplat_stereo.scene.gaussians import GaussianScene, decoded_scene

if TYPE_CHECKING:
    import torch

#: Coefficients above the DC term per SH degree (bands).
SH_COEFFS = (0, 3, 8, 15)
#: Version 1's centroid image widths, by bands.
V1_CENTROID_WIDTHS = {192: 1, 512: 2, 960: 3}
#: Largest SH palette ``save_sog`` builds (splat-transform goes to 65536; k-means here runs on the CPU or GPU).
SH_PALETTE_MAX = 4096
#: Opacity clamp of splat-transform's reader (its logit is clamped to logit(1e-6)).
OPACITY_EPS = 1e-6
WEBP_MAX_SIDE = 16383
#: libwebp's lossless effort (OpenImageIO's ``compression=lossless:<effort>``, 0..100, default 70) and method (0
#: fastest .. 6, OpenImageIO's default) of the per-Gaussian images, and the method of the SH palette's two images.
#: Method 0 encodes a 452x452 image in about 20 ms of one core (6: 1-2.5 s) into 4-20% more bytes; the labels
#: shrink most from method 1 on, for little time (docs/formats.md "The SOG writer": each image by method).
WEBP_EFFORT, WEBP_METHOD, WEBP_PALETTE_METHOD = 0, 0, 1


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


def write_webp(rgba: np.ndarray, width: int, height: int, method: int = WEBP_METHOD) -> bytes:
    """Lossless WebP bytes of uint8 RGBA texels [width * height, 4] (fewer are padded with zeros), alpha
    unassociated, at libwebp's ``method`` and ``WEBP_EFFORT``. Through ``ImageBuf.write``, which releases
    the GIL while libwebp encodes (``ImageOutput.close``, where OpenImageIO 3.1+ encodes, holds it), so that
    images in threads are encoded side by side."""
    import OpenImageIO as oiio

    img = np.zeros((height, width, 4), np.uint8)
    img.reshape(-1, 4)[:len(rgba)] = rgba
    spec = oiio.ImageSpec(width, height, 4, "uint8")
    spec.attribute("compression", f"lossless:{WEBP_EFFORT}")
    spec.attribute("webp:method", method)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    buf = oiio.ImageBuf(spec)
    with tempfile.TemporaryDirectory(prefix="sog-") as tmp:
        name = os.path.join(tmp, "image.webp")
        if not buf.set_pixels(oiio.ROI(), img) or not buf.write(name):
            raise SogError(f"OpenImageIO cannot write WebP: {buf.geterror() or oiio.geterror()}")
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
#: The per-Gaussian images, in the zip's order (``shN_labels.webp`` with SH only; ``shN_centroids.webp`` before it).
IMAGES = ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp", "shN_labels.webp")


@dataclass
class SogImage:
    """One image of a SOG to encode: uint8 RGBA texels [m, 4] (in the scene's order when ``order`` is given: the
    file's texel i is ``texels[order[i]]``), the image's width and height, libwebp's method."""

    texels: np.ndarray
    width: int
    height: int
    method: int = WEBP_METHOD
    order: np.ndarray | None = None

    def encode(self) -> bytes:
        """The image's lossless WebP bytes (``write_webp``)."""
        texels = self.texels if self.order is None else np.take(self.texels, self.order, axis=0)
        return write_webp(texels, self.width, self.height, self.method)


def image_names(degree: int) -> list[str]:
    """The images of a SOG of SH ``degree``, in the zip's order."""
    return [*IMAGES[:5], *(["shN_centroids.webp", IMAGES[5]] if degree else [])]


def quantise_sog(scene: GaussianScene, ready: Callable[[str, SogImage], object], path: str | os.PathLike = "<memory>",
                 sh_palette_max: int = SH_PALETTE_MAX, dev: torch.device | None = None) -> dict:
    """The quantisation of ``encode_sog`` (its docstring), in torch on ``dev`` (default ``row_tasks.device()``):
    ``ready(name, image)`` is called with each image as soon as its texels exist (in this thread, in the order of
    their encode times, longest first); returns the ``meta.json`` dict. ``SogError`` naming ``path`` for a scene
    a SOG cannot hold."""
    import torch  # only for writing: the readers do without it

    from scenesplat_stereo.scene import sog_texels

    n = len(scene)
    if n == 0:
        raise SogError(f"{path}: an empty scene has no SOG (images of at least one texel)")
    width = math.ceil(math.sqrt(n) / 4) * 4
    height = math.ceil(n / width / 4) * 4
    if max(width, height) > WEBP_MAX_SIDE:
        raise SogError(f"{path}: {n} Gaussians need {width}x{height} texels, beyond WebP's {WEBP_MAX_SIDE}")
    degree, dev = scene.sh_degree, dev or row_tasks.device()
    shn = None
    try:
        if degree:
            palette = min(64, 2 ** math.floor(math.log2(n / 1024))) * 1024 if n >= 1024 else n
            palette = max(1, min(palette, sh_palette_max, n))
            stream = torch.cuda.current_stream(dev) if dev.type == "cuda" else None  # this thread's, for the task
            shn = row_tasks.pool().submit(sog_texels.sh_palette, scene.sh, degree, palette, dev, stream)
        order = morton_order(scene.means, dev)
        ordered = functools.partial(SogImage, width=width, height=height, order=order)  # in the scene's order
        colour_rgba, colour_book = sog_texels.colour_texels(scene, dev)
        ready(IMAGES[4], ordered(colour_rgba))
        rgba, mins, maxs = sog_texels.placed(scene, dev)
        for name, texels in zip(IMAGES[:3], rgba):
            ready(name, ordered(texels))
        scale_rgba, scale_book = sog_texels.scale_texels(scene, dev)
        ready(IMAGES[3], ordered(scale_rgba))
        meta = {"version": 2, "asset": {"generator": "scenesplat_stereo.scene.sog"}, "count": n,
                "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
                "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
                "quats": {"files": ["quats.webp"]},
                "sh0": {"codebook": colour_book.tolist(), "files": ["sh0.webp"]}}
        if degree:
            book, px, centroid_rows, labels = shn.result()
            ready("shN_centroids.webp", SogImage(px, 64 * SH_COEFFS[degree], centroid_rows, WEBP_PALETTE_METHOD))
            ready(IMAGES[5], ordered(labels, method=WEBP_PALETTE_METHOD))
            meta["shN"] = {"count": palette, "bands": degree, "codebook": book.tolist(),
                           "files": ["shN_centroids.webp", "shN_labels.webp"]}
    finally:  # after an error, the palette's task is not left running
        if shn is not None:
            shn.cancel()
            wait([shn])
    return meta


def stored_zip(members: Iterable[tuple[str, bytes, int]]) -> Iterator[bytes]:
    """The bytes of a zip of ``members`` (ASCII name, data, its CRC-32), stored (no compression), dated 1980-01-01,
    as Python's ``zipfile`` writes ``ZipFile(f, "w").writestr(ZipInfo(name, (1980, 1, 1, 0, 0, 0)), data)``:
    yielded member by member as ``members`` gives them (a local header, then the data as it is), then the central
    directory. Archives reaching 2 GiB (``zipfile``'s switch to zip64) are refused."""
    central, offset = [], 0
    for name, data, crc in members:
        raw, size = name.encode("ascii"), len(memoryview(data))
        fields = struct.pack("<HHHHHIII", 20, 0, 0, 0, 33, crc, size, size)  # version 2.0, date 1980-01-01
        local = b"PK\x03\x04" + fields + struct.pack("<HH", len(raw), 0) + raw
        if offset + len(local) + size > zipfile.ZIP64_LIMIT:
            raise SogError(f"a SOG of {offset + len(local) + size:,} bytes: beyond the 2 GiB its zip is written to")
        yield local
        yield data
        central.append(b"PK\x01\x02" + struct.pack("<H", 0x0314) + fields  # made by: version 2.0, Unix
                       + struct.pack("<HHHHHII", len(raw), 0, 0, 0, 0, 0o600 << 16, offset) + raw)
        offset += len(local) + size
    directory = b"".join(central)
    yield directory + struct.pack("<4sHHHHIIH", b"PK\x05\x06", 0, 0, len(central), len(central), len(directory),
                                  offset, 0)


def _encoded(image: SogImage) -> tuple[bytes, int]:
    """(``image.encode()``, its CRC-32): a pool task's, so that the zip need not read the bytes again."""
    data = image.encode()
    return data, zlib.crc32(data)


@contextmanager
def _encodes() -> Iterator[dict[str, Future]]:
    """A dict for the images' encode futures (``_encoded``); on leaving, none is left running (after an error:
    cancelled)."""
    futures: dict[str, Future] = {}
    try:
        yield futures
    finally:
        for f in futures.values():
            f.cancel()
        wait(list(futures.values()))


def _bundled(futures: dict[str, Future], meta: dict) -> Iterator[bytes]:
    """The bundled ``.sog`` (``stored_zip``) of the images' encode futures in the zip's order (``image_names``),
    then ``meta.json``: each image yielded once its encode and those before it are done."""
    names = image_names(meta.get("shN", {}).get("bands", 0))
    text = json.dumps(meta).encode()
    members = ((name, *futures[name].result()) for name in names)
    return stored_zip(itertools.chain(members, [("meta.json", text, zlib.crc32(text))]))


def encode_images(images: dict[str, SogImage], meta: dict) -> Iterator[bytes]:
    """The bundled ``.sog`` of ``images`` encoded side by side in tasks of the shared pool (``row_tasks``), as its
    parts (``_bundled``: for ``atomic_write_bytes``, which writes each as it comes)."""
    pool = row_tasks.pool()
    with _encodes() as futures:
        futures.update((name, pool.submit(_encoded, image)) for name, image in images.items())
        yield from _bundled(futures, meta)


def _queue_encodes(scene: GaussianScene, futures: dict[str, Future], path: str | os.PathLike,
                   sh_palette_max: int) -> dict:
    """``quantise_sog``, each image's encode (``_encoded``) queued on the shared pool into ``futures`` as soon as its
    texels exist; returns the ``meta.json`` dict."""
    pool = row_tasks.pool()
    return quantise_sog(scene, lambda name, image: futures.__setitem__(name, pool.submit(_encoded, image)), path,
                        sh_palette_max)


def encode_sog(scene: GaussianScene, path: str | os.PathLike = "<memory>",
               sh_palette_max: int = SH_PALETTE_MAX) -> bytes:
    """The bundled ``.sog`` (zip) bytes of ``scene`` (module docstring).

    ``quantise_sog`` makes the SH palette in a task of the shared pool of ``row_tasks`` while this thread finds the
    Morton order and then quantises the texels in the scene's order with ``sog_texels`` (all of it in torch on
    ``row_tasks.device()``, a GPU where there is one): the colours, then the positions and quaternions, then the
    scales, the order of their images' encode times, longest first. Each image is gathered into Morton order and
    encoded in a pool task of its own as soon as its texels exist (``write_webp`` runs without the GIL), so the
    encodes overlap the rest of the quantisation. On a GPU that work is bound by the host's kernel launches: in
    one thread it takes as long as in three tasks side by side (docs/benchmarks.md "Issue 35: the SOG writer's
    encodes queued as their texels are ready"). Not to be called from a task of that pool (this function waits
    for tasks of it)."""
    with _encodes() as futures:
        return b"".join(_bundled(futures, _queue_encodes(scene, futures, path, sh_palette_max)))


def save_sog(scene: GaussianScene, path: str | os.PathLike, durable: bool = True) -> Path:
    """Write ``scene`` as a bundled version-2 ``.sog`` (``encode_sog``'s bytes), atomically. Returns the path. Each
    member of the zip is written as soon as its encode and those before it are done, while the later ones encode:
    what is left after the last encode is its member and the zip's directory (no copy of the whole into memory).
    A scene a SOG cannot hold is refused by the quantisation, before any file is opened."""
    path = Path(path)
    with _encodes() as futures:
        meta = _queue_encodes(scene, futures, path, SH_PALETTE_MAX)
        atomic_write_bytes(path, _bundled(futures, meta), durable=durable)
    return path
