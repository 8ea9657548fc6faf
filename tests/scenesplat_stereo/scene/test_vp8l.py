"""scenesplat_stereo.scene.vp8l: the lossless WebP encoder decoded by libwebp (through OpenImageIO, an independent
decoder) to the exact texels, for every transform it writes, degenerate and extreme images included; its parts
against independent versions written in the test (Huffman costs by merging, canonical codes by RFC 1951's
recurrence, bits packed one by one into a Python integer); and its choice of transforms against encoding every
candidate. splat-transform reading the SOG writer's images: tests/scenesplat_stereo/scene/test_sog.py."""

from __future__ import annotations

import heapq
import itertools
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from scenesplat_stereo.scene import vp8l

TRANSFORMS = list(itertools.product((False, True), vp8l.PREDICTORS))


def decoded(data: bytes, tmp_path: Path) -> np.ndarray:
    """The texels [h * w, 4] libwebp reads from ``data`` (alpha unassociated: RGB as stored)."""
    path = tmp_path / "image.webp"
    path.write_bytes(data)
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    assert inp is not None and inp.format_name() == "webp", oiio.geterror()
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
    inp.close()
    rgba = np.full((spec.width * spec.height, 4), 255, np.uint8)
    rgba[:, :spec.nchannels] = pixels.reshape(-1, spec.nchannels)
    return rgba, spec.width, spec.height


def images(width: int, height: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Texels [h * w, 4] of several kinds: random, smooth, one colour, two values a channel, alpha 0 with colours."""
    y, x = np.mgrid[:height, :width]
    smooth = np.stack([(x + y) % 256, (2 * x) % 256, (255 - y) % 256, np.full_like(x, 255)], -1).astype(np.uint8)
    hidden = rng.integers(0, 256, (height * width, 4), dtype=np.uint8)
    hidden[:, 3] = 0  # invisible texels: their colours must come back
    return {"random": rng.integers(0, 256, (height * width, 4), dtype=np.uint8), "smooth": smooth.reshape(-1, 4),
            "one colour": np.full((height * width, 4), 7, np.uint8),
            "two values": (rng.integers(0, 2, (height * width, 4)) * 200).astype(np.uint8), "alpha 0": hidden}


@pytest.mark.parametrize("width,height", [(1, 1), (1, 9), (9, 1), (3, 5), (37, 23), (513, 3), (4, 600)])
def test_libwebp_reads_every_transform_exactly(width: int, height: int, tmp_path: Path) -> None:
    rng = np.random.default_rng(width * 1000 + height)
    for kind, rgba in images(width, height, rng).items():
        for transforms in [None, *TRANSFORMS]:
            got, w, h = decoded(vp8l.encode(rgba, width, height, transforms), tmp_path)
            assert (w, h) == (width, height)
            assert np.array_equal(got, rgba), (kind, transforms)


def test_codes_at_the_length_limit_and_skewed_histograms(tmp_path: Path) -> None:
    """Fibonacci counts make a Huffman tree 25 deep: the codes are limited to 15 bits, complete, and decode."""
    fib = [1, 1]
    while len(fib) < 26:
        fib.append(fib[-1] + fib[-2])
    values = np.repeat(np.arange(26), fib).astype(np.uint8)
    np.random.default_rng(0).shuffle(values)
    assert vp8l.prefix_lengths(np.bincount(values), limit=64).max() == 25
    lengths = vp8l.prefix_lengths(np.bincount(values))
    assert lengths.max() <= vp8l.MAX_CODE_LENGTH and np.sum(2.0 ** -lengths[lengths > 0]) == 1.0
    width = 1000
    rgba = np.zeros((-(-len(values) // width) * width, 4), np.uint8)
    rgba[:len(values), 1], rgba[:len(values), 0], rgba[:, 3] = values, values[::-1], 255
    got, _, _ = decoded(vp8l.encode(rgba, width, len(rgba) // width, (False, None)), tmp_path)
    assert np.array_equal(got, rgba)


def huffman_cost(counts: list[int]) -> int:
    """Bits of an optimal prefix code of ``counts`` (two or more non-zero): the sum of every merge's weight."""
    heap = [c for c in counts if c]
    heapq.heapify(heap)
    cost = 0
    while len(heap) > 1:
        merged = heapq.heappop(heap) + heapq.heappop(heap)
        cost += merged
        heapq.heappush(heap, merged)
    return cost


def test_prefix_lengths_are_optimal_and_complete() -> None:
    rng = np.random.default_rng(5)
    for trial in range(30):
        counts = rng.integers(0, 1000, 256) * (rng.random(256) < rng.random())
        counts[rng.integers(0, 256, 2)] += 1  # at least two symbols
        free, lengths = vp8l.prefix_lengths(counts, limit=64), vp8l.prefix_lengths(counts)
        assert int((counts * free).sum()) == huffman_cost(counts.tolist()), trial
        if free.max() <= vp8l.MAX_CODE_LENGTH:
            assert np.array_equal(lengths, free)
        for got in (free, lengths):
            assert np.sum(2.0 ** -got[counts > 0]) == 1.0 and (got[counts == 0] == 0).all()
        assert lengths.max() <= vp8l.MAX_CODE_LENGTH
    assert vp8l.prefix_lengths(np.eye(256, dtype=np.int64)[9]).tolist() == [0] * 9 + [1] + [0] * 246
    assert not vp8l.prefix_lengths(np.zeros(40, np.int64)).any()


def test_canonical_codes_follow_the_deflate_recurrence() -> None:
    """RFC 1951 3.2.2: codes counted up within a length, lengths in increasing order; written first bit first."""
    rng = np.random.default_rng(6)
    for _ in range(20):
        counts = rng.integers(0, 50, 280) * (rng.random(280) < 0.6)
        counts[:2] += 1
        lengths = vp8l.prefix_lengths(counts)
        bl_count = np.bincount(lengths, minlength=16)
        bl_count[0] = 0
        next_code, code = [0] * 16, 0
        for bits in range(1, 16):
            code = (code + int(bl_count[bits - 1])) << 1
            next_code[bits] = code
        got = vp8l.canonical_codes(lengths)
        for symbol, length in enumerate(lengths.tolist()):
            if length:
                want = int(f"{next_code[length]:0{length}b}"[::-1], 2)
                next_code[length] += 1
                assert int(got[symbol]) == want


def test_pack_equals_bits_written_one_by_one() -> None:
    rng = np.random.default_rng(7)
    for start in (0, 1, 31, 32, 63, 100):
        lengths = rng.integers(0, 61, 500)
        values = np.array([int(rng.integers(0, 2 ** 62)) & ((1 << int(n)) - 1) for n in lengths], np.uint64)
        words, end = vp8l._pack(values, lengths, start)
        want, bit = 0, start
        for v, n in zip(values.tolist(), lengths.tolist()):
            want |= v << bit
            bit += n
        assert end == bit
        assert int.from_bytes(words.tobytes(), "little") == want


def test_the_chosen_transforms_are_within_a_percent_of_the_smallest() -> None:
    """On images with structure (a smooth ramp plus noise, a random walk along rows, noise), ``choose``'s
    estimate on every eighth row picks an encoding within 1% of the smallest of all candidates."""
    rng = np.random.default_rng(8)
    h, w = 128, 96
    y, x = np.mgrid[:h, :w]
    ramp = np.stack([x + y, 2 * y, x, 255 + 0 * x], -1) + rng.integers(0, 3, (h, w, 4))
    walk = np.cumsum(rng.integers(-2, 3, (h, w, 4)), axis=1) + 128
    green = rng.integers(0, 256, (h, w, 1)) + rng.integers(0, 4, (h, w, 4))  # R, B close to G
    for img in (ramp, walk, green, rng.integers(0, 256, (h, w, 4))):
        rgba = (img % 256).astype(np.uint8).reshape(-1, 4)
        sizes = [len(vp8l.encode(rgba, w, h, t)) for t in TRANSFORMS]
        assert len(vp8l.encode(rgba, w, h)) <= 1.01 * min(sizes)


def test_header_fields_and_alpha_hint() -> None:
    opaque = np.full((6 * 5, 4), 255, np.uint8)
    data = vp8l.encode(opaque, 6, 5)
    assert data[:4] == b"RIFF" and data[8:16] == b"WEBPVP8L" and int.from_bytes(data[4:8], "little") == len(data) - 8
    assert len(data) % 2 == 0 and data[20] == 0x2F
    bits = int.from_bytes(data[21:25], "little")
    assert (bits & 0x3FFF, (bits >> 14) & 0x3FFF, (bits >> 28) & 1, bits >> 29) == (5, 4, 0, 0)
    translucent = opaque.copy()
    translucent[3, 3] = 254
    assert (int.from_bytes(vp8l.encode(translucent, 6, 5)[21:25], "little") >> 28) & 1 == 1


def test_bad_arguments_are_refused() -> None:
    rgba = np.zeros((12, 4), np.uint8)
    for width, height in ((0, 12), (12, 0), (vp8l.MAX_SIDE + 1, 1)):
        with pytest.raises(ValueError, match="texels a side"):
            vp8l.encode(np.zeros((max(width * height, 1), 4), np.uint8), width, height)
    with pytest.raises(ValueError, match="12 texels"):
        vp8l.encode(rgba, 5, 3)
    with pytest.raises(ValueError, match="predictor mode 3"):
        vp8l.encode(rgba, 4, 3, (False, 3))
