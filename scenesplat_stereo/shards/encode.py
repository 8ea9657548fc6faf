"""Encoding rendered images to the bytes stored in shards (SPEC sections 4 and 5), through OpenImageIO.

- Colour images: 8-bit sRGB-as-rendered JPEG, quality ``JPEG_QUALITY`` (92, paper appendix B), 4:2:0
  chroma subsampling, baseline (non-progressive) coding.
- Valid masks: 8-bit single-channel PNG holding 0 or 255 (rendered alpha >= 0.5 -> 255), written with zlib.
- Left depth (``--with-depth``): single-channel float16 OpenEXR (ZIP), expected depth along the camera's
  z axis in world units (metres); 0 where nothing was rendered.
- Decoding (``decode_image``): any image OpenImageIO reads, turned upright by its EXIF Orientation tag.

Every encoder fixes all settings (and the EXR ``DateTime``, which OpenImageIO otherwise stamps with the
wall clock), so the same pixels always give the same bytes. OpenImageIO's Python bindings cannot write to
memory, so each call goes through a per-thread scratch file in the process's scratch folder (``common.scratch``:
in ``/dev/shm`` when it has 1 GiB free, else the system temp folder), read back and removed.

``encode_sample`` turns one ``SampleImages`` into its shard members; ``encode_pool.SampleEncoder`` runs it
in encoder threads or processes behind a bounded queue (this module imports nothing of that one).
"""

from __future__ import annotations

import os
import struct
import threading
import zlib
from dataclasses import dataclass

import numpy as np
import OpenImageIO as oiio

from scenesplat_stereo.common import scratch
from scenesplat_stereo.shards.sample import JPEG_QUALITY

JPEG_ENCODERS = ("cpu", "nvjpeg")  # where JPEGs are encoded: encoder workers, or the GPU (``nvjpeg``)

# Fixed so that EXR files do not carry the wall-clock time (byte-identical rebuilds).
_EXR_DATETIME = "1970:01:01 00:00:00"
_PNG_COMPRESSION_LEVEL = 6  # contact sheets and other images
# Masks are written here with zlib, not through OpenImageIO, which exposes neither zlib's strategy nor a
# way to write to memory: rows unfiltered, deflated at level 1 with the run-length strategy (Z_RLE). A
# 0/255 mask is long runs of one value, which Z_RLE codes without hash searches. Measured at 1752x1168
# (docs/benchmarks.md, issue 12): 4.2 ms and 5 KB per mask on the 16-core GPU host against 9.0 ms and
# 17 KB through OpenImageIO (Sub filter, level 1); 2.6-2.9 ms against 4.4 ms on a 2-core CPU.
_MASK_ZLIB_LEVEL = 1
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"\0\0\0\0IEND\xaeB`\x82"  # the empty IEND chunk with its CRC
_JPEG_SUBSAMPLING = "4:2:0"

_local = threading.local()


def _scratch_path(ext: str) -> str:
    """A scratch file name owned by the calling thread (one per extension)."""
    if getattr(_local, "pid", None) != os.getpid():
        _local.pid = os.getpid()
        _local.paths = {}
    if ext not in _local.paths:
        _local.paths[ext] = os.path.join(scratch.scratch_dir(), f"t{threading.get_ident()}.{ext}")
    return _local.paths[ext]


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8 by round(clip(x, 0, 1) * 255); uint8 passes through unchanged."""
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        return rgb
    if not np.issubdtype(rgb.dtype, np.floating):
        raise TypeError(f"image: expected uint8 or float in [0, 1], got dtype {rgb.dtype}")
    if not np.isfinite(rgb).all():
        raise ValueError(f"image: {int((~np.isfinite(rgb)).sum())} values are NaN or infinite")
    return np.rint(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def _write(arr: np.ndarray, ext: str, fmt: str, attrs: dict[str, object]) -> bytes:
    """Write arr [H, W, C] (C-contiguous) with OpenImageIO to a scratch file and return its bytes."""
    if arr.ndim != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"image: expected a non-empty [H, W, C] array, got shape {arr.shape}")
    arr = np.ascontiguousarray(arr)
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    for name, value in attrs.items():
        spec.attribute(name, value)
    path = _scratch_path(ext)
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise RuntimeError(f"OpenImageIO has no writer for .{ext}: {oiio.geterror()}")
    try:
        if not out.open(path, spec):
            raise RuntimeError(f"OpenImageIO could not open {path}: {out.geterror()}")
        if not out.write_image(arr):
            raise RuntimeError(f"OpenImageIO could not write {path}: {out.geterror()}")
        out.close()
        with open(path, "rb") as f:
            return f.read()
    finally:
        out.close()
        _remove(path)


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def encode_jpeg(rgb: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """RGB image [H, W, 3] (uint8, or float in [0, 1] rounded to uint8) -> JPEG bytes at ``quality``."""
    rgb = to_uint8(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"encode_jpeg: expected an [H, W, 3] image, got shape {rgb.shape}")
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"encode_jpeg: quality must be in 1..100, got {quality}")
    attrs = {"Compression": f"jpeg:{int(quality)}", "jpeg:subsampling": _JPEG_SUBSAMPLING}
    return _write(rgb, "jpg", "uint8", attrs)


def encode_png(image: np.ndarray) -> bytes:
    """8-bit image [H, W, C] (uint8, or float in [0, 1] rounded to uint8) -> PNG bytes (e.g. contact sheets)."""
    image = to_uint8(image)
    if image.ndim != 3:
        raise ValueError(f"encode_png: expected an [H, W, C] image, got shape {image.shape}")
    return _write(image, "png", "uint8", {"png:compressionLevel": _PNG_COMPRESSION_LEVEL})


def encode_mask_png(mask: np.ndarray) -> bytes:
    """Boolean mask [H, W] -> 8-bit single-channel PNG bytes holding 0 (False) and 255 (True): one IHDR
    (8-bit greyscale, no interlace), one IDAT (unfiltered rows, zlib Z_RLE) and IEND."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"encode_mask_png: expected a bool [H, W] mask, got {mask.dtype} {mask.shape}")
    return encode_mask_pngs(mask[None])[0]  # which checks the dtype and the size


def encode_mask_pngs(masks: np.ndarray) -> list[bytes]:
    """Boolean masks [T, H, W] -> T PNGs as ``encode_mask_png`` writes them; the rows of all T are laid
    out in one array (two array operations per sample instead of two per mask)."""
    masks = np.asarray(masks)
    if masks.dtype != np.bool_ or masks.ndim != 3 or 0 in masks.shape[1:]:
        raise ValueError(f"encode_mask_pngs: expected non-empty bool [T, H, W] masks, got {masks.dtype} {masks.shape}")
    t, h, w = masks.shape
    rows = np.zeros((t, h, w + 1), np.uint8)  # each row: filter type 0 (none), then its pixels
    np.negative(masks.view(np.uint8), out=rows[:, :, 1:])  # 1 -> 255 (uint8 wraps), 0 -> 0
    head = _PNG_SIGNATURE + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
    out = []
    for r in rows:
        deflate = zlib.compressobj(_MASK_ZLIB_LEVEL, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
        out.append(head + _png_chunk(b"IDAT", deflate.compress(r) + deflate.flush()) + _PNG_END)
    return out


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    """One PNG chunk: length, type, data, CRC-32 of type + data (big-endian)."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_depth_exr(depth: np.ndarray) -> bytes:
    """Depth [H, W] (world units along the camera z axis) -> single-channel float16 EXR bytes (ZIP).

    Values above float16's range (65504) become +inf; NaN is refused."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"encode_depth_exr: expected an [H, W] depth map, got shape {depth.shape}")
    if np.isnan(depth).any():
        raise ValueError(f"encode_depth_exr: depth has {int(np.isnan(depth).sum())} NaN values")
    attrs = {"compression": "zip", "DateTime": _EXR_DATETIME}
    return _write(depth[:, :, None], "exr", "half", attrs)


#: EXIF Orientation (TIFF tag 274) -> how the stored pixels [H, W, C] become the upright image (1 and unknown
#: values: as stored): 2 mirrored left-right, 3 turned 180 deg, 4 mirrored top-bottom, 5 transposed, 6 turned
#: 90 deg clockwise, 7 transversed, 8 turned 90 deg anticlockwise (as OpenCV's imread; tests/commands/test_bad_input_model.py).
_UPRIGHT = {
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: a.transpose(1, 0, 2),
    6: lambda a: a.transpose(1, 0, 2)[:, ::-1],
    7: lambda a: a[::-1, ::-1].transpose(1, 0, 2),
    8: lambda a: a.transpose(1, 0, 2)[::-1],
}


def decode_image(data: bytes, ext: str) -> np.ndarray:
    """Decode image bytes of type ``ext`` ("jpg", "png", "exr", with or without a dot) with OpenImageIO.

    Returns [H, W, C] upright (an EXIF Orientation tag other than 1, as phones write, is applied; H and W
    are then those of the upright image) in the file's pixel type: uint8 for JPEG and PNG, float32 for
    (half) EXR. Raises ValueError when the bytes do not decode.
    """
    ext = ext.lower().lstrip(".")
    path = _scratch_path("in." + ext)
    with open(path, "wb") as f:
        f.write(data)
    try:
        inp = oiio.ImageInput.open(path)
        if inp is None:
            raise ValueError(f"decode_image: not a readable .{ext} image ({len(data)} bytes): {oiio.geterror()}")
        try:
            spec = inp.spec()
            fmt = "float" if spec.format.basetype in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE) else "uint8"
            arr = inp.read_image(fmt)
            if arr is None or inp.has_error:
                raise ValueError(f"decode_image: truncated or corrupt .{ext} image: {inp.geterror()}")
            orientation = spec.get_int_attribute("Orientation", 1)
        finally:
            inp.close()
    finally:
        _remove(path)
    arr = np.asarray(arr).reshape(spec.height, spec.width, spec.nchannels)
    upright = _UPRIGHT.get(orientation)
    return arr if upright is None else np.ascontiguousarray(upright(arr))


@dataclass
class SampleImages:
    """The rendered images of one sample, ready to encode (already uint8 / bool on the CPU).

    ``left``/``right`` [H, W, 3] uint8; ``targets`` [T, H, W, 3] uint8 and ``masks`` [T, H, W] bool in
    the order of ``target_ids`` (the Fibonacci direction index j of each target); ``depth`` [H, W] float32
    (left camera, world units) or None; ``meta`` the sample's JSON bytes. ``jpegs``: the colour images
    already encoded (on the GPU, ``nvjpeg``), member name -> bytes for every name of ``jpeg_members``;
    ``left``, ``right`` and ``targets`` are then None.
    """

    key: str
    left: np.ndarray | None
    right: np.ndarray | None
    targets: np.ndarray | None
    masks: np.ndarray
    target_ids: tuple[int, ...]
    meta: bytes
    depth: np.ndarray | None = None
    jpegs: dict[str, bytes] | None = None


def jpeg_members(target_ids: tuple[int, ...]) -> list[str]:
    """The JPEG members of a sample (SPEC section 5), in the order left, right, targets."""
    return ["left.jpg", "right.jpg"] + [f"target_{j:02d}.jpg" for j in target_ids]


def encode_sample(sample: SampleImages, quality: int = JPEG_QUALITY) -> dict[str, bytes]:
    """Encode one sample into its shard members (SPEC section 5): ``left.jpg``, ``right.jpg`` and
    ``target_<jj>.jpg`` (taken as they are from ``sample.jpegs`` when given), then ``encode_other_members``."""
    if sample.jpegs is not None:
        jpegs = dict(sample.jpegs)
    else:
        images = [sample.left, sample.right, *sample.targets]
        jpegs = {name: encode_jpeg(image, quality) for name, image in zip(jpeg_members(sample.target_ids), images)}
    return jpegs | encode_other_members(sample)


def encode_other_members(sample: SampleImages) -> dict[str, bytes]:
    """The members of a sample other than its JPEGs: ``mask_<jj>.png`` for each target direction jj,
    ``left_depth.exr`` when depth is given, and ``json``."""
    names = [f"mask_{j:02d}.png" for j in sample.target_ids]
    members = dict(zip(names, encode_mask_pngs(sample.masks))) if names else {}
    if sample.depth is not None:
        members["left_depth.exr"] = encode_depth_exr(sample.depth)
    members["json"] = sample.meta
    return members
