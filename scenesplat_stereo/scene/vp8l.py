"""WebP lossless (VP8L) encoding in numpy, for images whose texels are close to random: one spatial predictor for
the whole image, the subtract-green transform where it helps, and one canonical prefix code per channel. No LZ77
back references and no colour cache: every texel is four prefix-coded literals (green, red, blue, alpha), so its
bit position in the stream is a cumulative sum of code lengths and the whole image packs in a few vectorised
passes instead of libwebp's sequential parse.

Written from the WebP lossless bitstream specification (RFC 9649): the RIFF container with one ``VP8L`` chunk;
the header (signature 0x2f, 14-bit width - 1 and height - 1, the alpha-is-used hint, version 0); the transforms
in the order they were applied (subtract green, then a predictor transform of one block of 2^9 texels a side per
512 x 512 pixels, all blocks the same mode); the image's colour-cache bit (0), meta-prefix bit (0), its five
prefix codes (green's alphabet 256 + 24, red, blue, alpha 256, distance 40), each a *simple* code where one or
two literals are used and else a *normal* code (its lengths coded by the 19-symbol code-length code in
``CODE_LENGTH_ORDER``, with runs of zeros as symbols 17/18 and repeats as 16); then the texels. Bits are written
least significant first; a prefix code's bits from its first (most significant) bit on, as its decoders read them.
The predictor, for texel (x, y) of the (subtract-green) image, is the image's mode except on the borders: texel
(0, 0) is predicted by A = 255, RGB = 0; the rest of the top row by L (the left texel); the left column by T
(the texel above). Residuals are taken modulo 256 per channel. Texels whose alpha is 0 keep their colour (libwebp
drops it unless told to keep it exact).

The transforms are chosen per image by the Shannon entropy of the residuals of every ``SAMPLE_STEP``-th row
(``choose``): predictors 1 (L), 2 (T) and 7 (the average of L and T), or none, each with and without subtract
green. On the SOG writer's per-Gaussian images this gives files as small as libwebp's method 0 or smaller, in a
fraction of its time (docs/formats.md "The SOG writer").
"""

from __future__ import annotations

import struct

import numpy as np

#: Longest prefix code and longest code-length code (the format's limits).
MAX_CODE_LENGTH, MAX_LENGTH_CODE_LENGTH = 15, 7
#: The order in which the code-length code's 19 lengths are written.
CODE_LENGTH_ORDER = (17, 18, 0, 1, 2, 3, 4, 5, 16, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
#: Alphabet sizes of the five prefix codes: green (literals and 24 LZ77 length prefixes; no colour cache), red,
#: blue, alpha, distance.
ALPHABETS = (256 + 24, 256, 256, 256, 40)
#: Predictor modes tried (RFC 9649 4.1): L, T, and Average2(L, T); ``None`` is no predictor transform.
PREDICTORS = (None, 1, 2, 7)
#: log2 of the predictor's block side (the largest the format has: ``ReadBits(3) + 2`` = 9).
PREDICTOR_BITS = 9
#: ``choose`` estimates each candidate's entropy on every SAMPLE_STEP-th row (all rows of images below 64 rows).
SAMPLE_STEP = 8
#: Largest width and height of a WebP image (libwebp's ``WEBP_MAX_DIMENSION``; VP8L's 14-bit fields hold 16384).
MAX_SIDE = 16383
#: Bit at which a packed (code, length) table entry keeps its length: codes of two channels take at most 30 bits.
_LENGTH_SHIFT = 58


class BitWriter:
    """Bits least significant first, as VP8L reads them: ``put(value, n)`` appends the ``n`` low bits of value."""

    def __init__(self) -> None:
        self.value, self.bits = 0, 0

    def put(self, value: int, n: int) -> None:
        self.value |= (value & ((1 << n) - 1)) << self.bits
        self.bits += n


def _huffman_depths(weights: list[int]) -> list[int]:
    """Depths of the leaves of the Huffman tree of ``weights`` (at least two, ascending), by the two-queue method:
    the two lightest of the unmerged leaves and merged nodes are merged, leaves first on ties."""
    m = len(weights)
    weight, parent = weights + [0] * (m - 1), [0] * (2 * m - 1)
    leaf, node = 0, m
    for new in range(m, 2 * m - 1):
        pair = []
        for _ in range(2):
            if leaf < m and (node >= new or weight[leaf] <= weight[node]):
                pair.append(leaf)
                leaf += 1
            else:
                pair.append(node)
                node += 1
        weight[new] = weight[pair[0]] + weight[pair[1]]
        parent[pair[0]] = parent[pair[1]] = new
    depth = [0] * (2 * m - 1)
    for i in range(2 * m - 3, -1, -1):
        depth[i] = depth[parent[i]] + 1
    return depth[:m]


def prefix_lengths(counts: np.ndarray, limit: int = MAX_CODE_LENGTH) -> np.ndarray:
    """Huffman code lengths (int64, 0 for unused symbols) of symbol ``counts``, none above ``limit``: the Huffman
    tree of the counts, and where that is deeper than ``limit``, of the counts raised to a floor doubled until it
    is not (libwebp's way). A single used symbol gets length 1 (the code the format reads with no bits); no symbol
    used gives all zeros."""
    counts = np.asarray(counts, np.int64)
    lengths = np.zeros(len(counts), np.int64)
    used = np.flatnonzero(counts)
    if len(used) <= 1:
        lengths[used] = 1
        return lengths
    floor = 1
    while True:
        weights = np.maximum(counts[used], floor)
        order = np.argsort(weights, kind="stable")
        depths = _huffman_depths(weights[order].tolist())
        if max(depths) <= limit:
            lengths[used[order]] = depths
            return lengths
        floor *= 2


#: Bits of 0..2^15 - 1 reversed (15 bits), for the codes' bit order.
_REVERSED = np.zeros(1 << MAX_CODE_LENGTH, np.uint64)
for _bit in range(MAX_CODE_LENGTH):
    _REVERSED |= ((np.arange(1 << MAX_CODE_LENGTH, dtype=np.uint64) >> np.uint64(_bit)) & np.uint64(1)) \
        << np.uint64(MAX_CODE_LENGTH - 1 - _bit)


def canonical_codes(lengths: np.ndarray) -> np.ndarray:
    """The canonical prefix codes of ``lengths`` (at most 15; shorter codes first, then by symbol), each with its
    bits reversed so that ``BitWriter.put(code, length)`` writes its first bit first (uint64; 0 for unused
    symbols). Code i of the sorted used symbols is the Kraft sum of those before it, in units of 2^-length."""
    lengths = np.asarray(lengths, np.int64)
    order = np.lexsort((np.arange(len(lengths)), lengths))
    order = order[lengths[order] > 0]
    units = np.int64(1) << (MAX_CODE_LENGTH - lengths[order])
    kraft = np.cumsum(units) - units  # in units of 2^-15: a multiple of each code's own unit
    codes = np.zeros(len(lengths), np.uint64)
    codes[order] = _REVERSED[kraft]  # the code's L bits, at the top of 15, reversed: at the bottom
    return codes


def _length_tokens(lengths: np.ndarray) -> list[tuple[int, int, int]]:
    """The code-length symbols of ``lengths`` as (symbol, extra bits' value, their count): runs of 3-138 zeros as
    17 / 18, a length repeated 3-6 times after it was written as 16, the rest as themselves."""
    tokens, i, n, values = [], 0, len(lengths), lengths.tolist()
    while i < n:
        v, run = values[i], 1
        while i + run < n and values[i + run] == v:
            run += 1
        i += run
        if v == 0:
            while run >= 11:
                take = min(run, 138)
                tokens.append((18, take - 11, 7))
                run -= take
            if run >= 3:
                tokens.append((17, run - 3, 3))
                run = 0
            tokens += [(0, 0, 0)] * run
        else:
            tokens.append((v, 0, 0))
            run -= 1
            while run >= 3:
                take = min(run, 6)
                tokens.append((16, take - 3, 2))
                run -= take
            tokens += [(v, 0, 0)] * run
    return tokens


def write_prefix_code(out: BitWriter, lengths: np.ndarray) -> np.ndarray:
    """Write the prefix code of ``lengths`` (``prefix_lengths``) and return the lengths its symbols are *written*
    with: a simple code (one or two symbols below 256) or a normal one. A code of one symbol is read with no bits,
    so its returned length is 0."""
    lengths = np.asarray(lengths, np.int64)
    used = np.flatnonzero(lengths)
    if len(used) <= 2 and (len(used) == 0 or used[-1] < 256):
        symbols = used.tolist() or [0]
        out.put(1, 1)  # simple code
        out.put(len(symbols) - 1, 1)
        first_8bits = int(symbols[0] > 1)
        out.put(first_8bits, 1)
        out.put(symbols[0], 1 + 7 * first_8bits)
        if len(symbols) == 2:
            out.put(symbols[1], 8)
        return lengths if len(used) == 2 else np.zeros_like(lengths)
    tokens = _length_tokens(lengths)
    token_lengths = prefix_lengths(np.bincount([t[0] for t in tokens], minlength=19), MAX_LENGTH_CODE_LENGTH)
    token_codes = canonical_codes(token_lengths)
    in_order = [int(token_lengths[s]) for s in CODE_LENGTH_ORDER]
    if np.count_nonzero(token_lengths) == 1:  # a code-length code of one symbol is read with no bits
        token_lengths = np.zeros_like(token_lengths)
    count = max(4, max(i + 1 for i, v in enumerate(in_order) if v))
    out.put(0, 1)  # normal code
    out.put(count - 4, 4)
    for v in in_order[:count]:
        out.put(v, 3)
    out.put(0, 1)  # as many lengths as the alphabet has symbols
    for symbol, extra, n in tokens:
        out.put(int(token_codes[symbol]), int(token_lengths[symbol]))
        out.put(extra, n)
    return lengths


def subtract_green(img: np.ndarray) -> np.ndarray:
    """The subtract-green transform of uint8 RGBA texels [..., 4]: R - G and B - G modulo 256."""
    out = img.copy()
    out[..., 0] -= img[..., 1]
    out[..., 2] -= img[..., 1]
    return out


def _predicted_rows(cur: np.ndarray, above: np.ndarray, mode: int) -> np.ndarray:
    """Predictions of rows ``cur`` [r, w, 4] (not the image's first) given the rows ``above`` them: the left column
    by T, the rest by ``mode``."""
    pred = np.empty_like(cur)
    pred[:, 0] = above[:, 0]
    left, top = cur[:, :-1], above[:, 1:]
    if mode == 1:
        pred[:, 1:] = left
    elif mode == 2:
        pred[:, 1:] = top
    elif mode == 7:  # Average2(L, T) = (L + T) >> 1 in uint8 without overflow
        pred[:, 1:] = (left >> 1) + (top >> 1) + (left & top & 1)
    else:
        raise ValueError(f"predictor mode {mode} is not one of {PREDICTORS[1:]}")
    return pred


def residuals(img: np.ndarray, mode: int | None) -> np.ndarray:
    """The residual image (uint8 [h, w, 4], modulo 256) of predictor ``mode`` on ``img`` (RFC 9649 4.1, borders
    included); ``img`` itself for ``None``."""
    if mode is None:
        return img
    out = np.empty_like(img)
    first = img[0]
    out[0, 0] = first[0] - np.array([0, 0, 0, 255], np.uint8)
    out[0, 1:] = first[1:] - first[:-1]
    out[1:] = img[1:] - _predicted_rows(img[1:], img[:-1], mode)
    return out


def _entropy_bits(samples: np.ndarray) -> float:
    """Shannon entropy, in bits, of uint8 ``samples`` [m, 4] coded one prefix code per channel."""
    total = 0.0
    for c in range(4):
        counts = np.bincount(samples[:, c], minlength=256)
        p = counts[counts > 0] / len(samples)
        total -= float((p * np.log2(p)).sum()) * len(samples)
    return total


def choose(img: np.ndarray) -> tuple[bool, int | None]:
    """(subtract green, predictor mode) of ``img`` [h, w, 4] with the fewest bits of residual entropy over every
    ``SAMPLE_STEP``-th row (the first excluded; every row of an image below 8 sample rows), among ``PREDICTORS``
    with and without subtract green; ties go to the earlier (no subtract green, no predictor)."""
    h = img.shape[0]
    if h < 2:
        return False, None
    step = SAMPLE_STEP if h >= 8 * SAMPLE_STEP else 1
    rows = np.arange(1, h, step)
    best = None
    for green in (False, True):
        src = subtract_green(img) if green else img
        cur, above = src[rows], src[rows - 1]
        for mode in PREDICTORS:
            res = cur if mode is None else cur - _predicted_rows(cur, above, mode)
            bits = _entropy_bits(res.reshape(-1, 4))
            if best is None or bits < best[0]:
                best = (bits, green, mode)
    return best[1], best[2]


def _table(first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Packed entries [256, 256] of two channels' (codes, written lengths), at [second's byte, first's byte]: the
    first channel's code, then the second's, their total length in bits 58-63."""
    c1, c2 = (c[:256].astype(np.uint64) for c in (first[0], second[0]))
    l1, l2 = (n[:256].astype(np.uint64) for n in (first[1], second[1]))
    code = c1[None, :] | (c2[:, None] << l1[None, :])
    return code | ((l1[None, :] + l2[:, None]) << np.uint64(_LENGTH_SHIFT))


def _pack(values: np.ndarray, lengths: np.ndarray, start: int) -> tuple[np.ndarray, int]:
    """``values`` (uint64 of at most 60 bits, ``lengths`` bits each) one after another from bit ``start`` on, as
    little-endian uint32 words, and the bit after the last. Each value's bits fall in at most three 32-bit words;
    the bits of different values do not overlap, so each word is the sum of its parts (``np.bincount``, exact in
    float64 below 2^53)."""
    ends = np.cumsum(lengths, dtype=np.int64) + start
    offsets = ends - lengths
    word, shift = offsets >> 5, (offsets & 31).astype(np.uint64)
    low32, one = np.uint64(0xFFFFFFFF), np.uint64(1)
    parts = ((values << shift) & low32,  # v << s, 32 bits at a time
             ((values >> one) >> (np.uint64(31) - shift)) & low32,
             ((values >> np.uint64(32)) >> (np.uint64(31) - shift)) >> one)
    end = int(ends[-1]) if len(ends) else start
    size = end // 32 + 3
    words = sum(np.bincount(word + k, part.astype(np.float64), size) for k, part in enumerate(parts))
    return words.astype(np.uint32), end


def encode(rgba: np.ndarray, width: int, height: int, transforms: tuple[bool, int | None] | None = None) -> bytes:
    """Lossless WebP file bytes of uint8 RGBA texels (``[height, width, 4]`` or ``[height * width, 4]``, row-major
    from the top-left, alpha unassociated). ``transforms``: (subtract green, predictor mode) to use instead of
    ``choose``'s."""
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise ValueError(f"a lossless WebP is 1..{MAX_SIDE} texels a side, not {width}x{height}")
    if np.size(rgba) != width * height * 4:
        raise ValueError(f"{np.size(rgba) // 4} texels for a {width}x{height} WebP image")
    img = np.ascontiguousarray(rgba, np.uint8).reshape(height, width, 4)
    green, mode = transforms if transforms is not None else choose(img)
    if mode is not None and mode not in PREDICTORS:
        raise ValueError(f"predictor mode {mode} is not one of {PREDICTORS[1:]}")
    out = BitWriter()
    out.put(0x2F, 8)
    out.put(width - 1, 14)
    out.put(height - 1, 14)
    out.put(int((img[..., 3] != 255).any()), 1)
    out.put(0, 3)
    src = img
    if green:
        out.put(1, 1)
        out.put(2, 2)  # SUBTRACT_GREEN
        src = subtract_green(img)
    if mode is not None:
        out.put(1, 1)
        out.put(0, 2)  # PREDICTOR_TRANSFORM, then its block size and its image: every block this mode
        out.put(PREDICTOR_BITS - 2, 3)
        out.put(0, 1)  # no colour cache
        for symbol in (mode, 0, 0, 0, 0):  # green holds the mode: one symbol a code, read with no bits
            write_prefix_code(out, np.arange(256) == symbol)
    out.put(0, 1)  # end of transforms
    res = residuals(src, mode).reshape(-1, 4)
    out.put(0, 1)  # no colour cache
    out.put(0, 1)  # one prefix code group for the whole image
    written = []
    for channel, alphabet in zip((1, 0, 2, 3), ALPHABETS):  # green, red, blue, alpha
        lengths = np.zeros(alphabet, np.int64)
        lengths[:256] = prefix_lengths(np.bincount(res[:, channel], minlength=256))
        written.append((canonical_codes(lengths), write_prefix_code(out, lengths)))  # (codes, written lengths)
    write_prefix_code(out, np.zeros(ALPHABETS[4], np.int64))  # no distances
    green_, red_, blue_, alpha_ = written
    pairs = res.view(np.uint16)  # little-endian: red | green << 8, blue | alpha << 8
    first = _table(green_, red_).T.reshape(-1)[pairs[:, 0]]  # at [green, red]: red | green << 8
    second = _table(blue_, alpha_).reshape(-1)[pairs[:, 1]]  # at [alpha, blue]
    mask = np.uint64((1 << _LENGTH_SHIFT) - 1)
    shift = np.uint64(_LENGTH_SHIFT)
    n1, n2 = first >> shift, second >> shift
    values = (first & mask) | ((second & mask) << n1)
    bits = (n1 + n2).astype(np.int64)
    words, end = _pack(values, bits, out.bits)
    data = bytearray(words.view(np.uint8)[:(end + 7) // 8].tobytes())
    head = out.value.to_bytes((out.bits + 7) // 8, "little")
    data[:len(head)] = (int.from_bytes(data[:len(head)], "little") | out.value).to_bytes(len(head), "little")
    chunk = b"VP8L" + struct.pack("<I", len(data)) + bytes(data) + b"\0" * (len(data) & 1)
    return b"RIFF" + struct.pack("<I", 4 + len(chunk)) + b"WEBP" + chunk
