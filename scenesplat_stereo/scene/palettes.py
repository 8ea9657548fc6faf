"""Codebooks and palettes for the SOG writer (``sog.encode_sog``): a 1-D codebook of scalar values, the nearest
entry of each value (``Nearest``), and a k-means palette of vectors (the higher SH coefficients).

The quantities are whatever the caller quantises (natural-log scales, SH coefficients: unitless); nothing here
depends on the order of the values except which rows the palette's k-means samples.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from scenesplat_stereo.scene import row_tasks

#: Cells of the grid through which ``Nearest`` looks labels up (fine enough that only 1-3% of real log-scales
#: and colours fall near a midpoint of their 256-entry codebook).
LOOKUP_CELLS = 1 << 16


def codebook(values: np.ndarray | torch.Tensor, k: int = 256, alpha: float = 0.2, bins: int = 1 << 14,
             iterations: int = 30) -> np.ndarray:
    """A 1-D codebook of ``values`` (any shape; a tensor on any device, its histogram made there): k ascending
    float32 entries (the last repeated when fewer distinct ones were found).

    Density-weighted k-means, as splat-transform's ``quantize1d`` (which takes alpha 0.5 and an exact dynamic
    programme): the values are binned into a ``bins``-bin histogram over their range (``histogram``), each bin weighs
    count^alpha (so sparse tails get entries that plain k-means would give the dense middle), and Lloyd's
    iterations start from weighted quantiles (on the CPU: they see only the bins). alpha 0.2 gave the smallest RMS
    and largest errors of 0.5, 0.3, 0.2, 0.1 on the guitar's log-scales and colours."""
    flat = torch.as_tensor(values).to(torch.float64).reshape(-1)
    lo, hi = torch.stack(torch.aminmax(flat)).tolist()
    if hi - lo < 1e-20:
        return np.full(k, lo, np.float32)
    counts, edges = histogram(flat, bins, lo, hi)
    x = 0.5 * (edges[1:] + edges[:-1])[counts > 0]
    w = counts[counts > 0].astype(np.float64) ** alpha
    cw, cwx = np.concatenate([[0.0], np.cumsum(w)]), np.concatenate([[0.0], np.cumsum(w * x)])
    centres = np.unique(np.interp((np.arange(k) + 0.5) / k * cw[-1], cw[1:], x))
    for _ in range(iterations):
        cut = np.searchsorted(x, 0.5 * (centres[1:] + centres[:-1]))
        start, end = np.concatenate([[0], cut]), np.concatenate([cut, [len(x)]])
        weight = cw[end] - cw[start]
        centres = np.unique(np.where(weight > 0, (cwx[end] - cwx[start]) / np.where(weight > 0, weight, 1), centres))
    return np.concatenate([centres, np.full(k - len(centres), centres[-1])]).astype(np.float32)


def histogram(flat: torch.Tensor, bins: int, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """(counts [bins] int64, edges [bins + 1] float64) of float64 values ``flat`` in [lo, hi] (lo < hi; a tensor on
    any device): value v in bin floor((v - lo) bins / (hi - lo)), the last bin closed. ``np.histogram``'s bins in
    a third of its time, but for a value within rounding of an edge, which may land in the bin on the edge's other
    side (``np.histogram`` checks each value against the edges)."""
    cell = ((flat - lo) * (bins / (hi - lo))).long()  # truncation is the floor: flat - lo >= 0
    counts = torch.bincount(cell.clamp_(max=bins - 1), minlength=bins)
    return counts.cpu().numpy(), np.linspace(lo, hi, bins + 1)


class Nearest:
    """The nearest entry of an ascending codebook ``book`` (at most 256 entries): ``Nearest(book, device)(values)``
    are uint8 labels (a tensor on ``device``, shaped like ``values``, finite), the number of midpoints of
    consecutive entries (float64) below each value, at most len(book) - 1 (a value on a midpoint takes the lower
    entry): ``torch.searchsorted``'s.

    A binary search over 255 midpoints costs about 60 ns a value on a CPU; instead the value's cell c of
    ``LOOKUP_CELLS`` equal cells over [book[0], book[-1]] is computed (clipped to the first and last), and where no
    midpoint lies in cells c - 1 to c + 1 the label is the count below cell c - 1. Cells are kept over 2^40 times
    wider than the float64 spacing of the book's values, so rounding moves a value's cell by far less than one
    cell and it lies within those three; the 1-3% of values near a midpoint are searched exactly. The table is
    made once for all the values labelled with it."""

    def __init__(self, book: np.ndarray, device: torch.device | str = "cpu"):
        self.book = book
        b = torch.as_tensor(np.asarray(book, np.float64), device=device)
        self.mids, self.lo, hi = 0.5 * (b[1:] + b[:-1]), float(book[0]), float(book[-1])
        self.scale, self.below = 0.0, None  # below: midpoints below each cell's lower neighbour
        if (hi - self.lo) / LOOKUP_CELLS > 2.0**-40 * max(abs(self.lo), abs(hi)):  # else a flat or too narrow book
            g, inf = LOOKUP_CELLS, torch.tensor([np.inf], dtype=torch.float64, device=device)
            grid = self.lo + (hi - self.lo) * (torch.arange(g + 1, dtype=torch.float64, device=device) / g)
            below = torch.searchsorted(self.mids, torch.cat([-inf, grid, inf]))
            self.scale, self.below = g / (hi - self.lo), below.to(torch.uint8)  # at most 255

    def __call__(self, values: np.ndarray | torch.Tensor) -> torch.Tensor:
        values = torch.as_tensor(values, device=self.mids.device)
        v = values.to(torch.float64).reshape(-1)
        if self.below is None:
            labels = torch.searchsorted(self.mids, v)
        else:
            cell = ((v - self.lo) * self.scale).clamp_(0, LOOKUP_CELLS - 1).long()  # far outside: the end cells
            labels = self.below.index_select(0, cell)
            near = torch.nonzero(labels != self.below[3:].index_select(0, cell)).squeeze(1)
            labels[near] = torch.searchsorted(self.mids, v[near]).to(torch.uint8)
        return labels.clamp_(max=len(self.mids)).to(torch.uint8).reshape(values.shape)


def kmeans(x: np.ndarray | torch.Tensor, k: int, dev: torch.device | None = None, iterations: int = 5,
           fit_rows: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """k-means of rows x [N, D] (an array, or a tensor already on ``dev``; torch on ``dev``, default
    ``row_tasks.device()``: CUDA when there): (centroids [k, D] float32, labels [N] int64 of every row's nearest
    centroid). Lloyd's iterations run on a random ``fit_rows`` k of the rows (all when fewer; the same rows for
    every x of N rows: ``permutation``), starting from k of them.

    The centroids' sums are taken on the CPU (at most ``fit_rows`` k rows), so the palette is the same from run to
    run on a GPU too. 5 iterations: 10 (the earlier count) gave 0.2-0.9% smaller RMS errors on a real prediction
    (SH 2), the skull capture (SH 3) and the synthetic bench scene, at twice the time. Distances are |c|^2 - 2 x.c in
    blocks of rows (about 4 MiB on the CPU, 256 MiB on a GPU); on the CPU numpy takes the argmin (torch's is several
    times slower there)."""
    dev = dev or row_tasks.device()
    X = torch.as_tensor(x, dtype=torch.float32, device=dev).contiguous()
    rows = permutation(len(X)).to(dev)
    fit = X[rows[:fit_rows * k]]
    C = fit[:k].clone()
    block = max(1, (1 << (26 if dev.type == "cuda" else 20)) // k)  # rows a block of distances

    def assign(points: torch.Tensor) -> torch.Tensor:
        c2, m2ct = (C * C).sum(1), (-2.0 * C).T.contiguous()
        out = torch.empty(len(points), dtype=torch.int64, device=dev)
        for i in range(0, len(points), block):
            d = torch.addmm(c2, points[i:i + block], m2ct)
            out[i:i + block] = d.argmin(1) if d.is_cuda else torch.from_numpy(d.numpy().argmin(1))
        return out

    fit_cpu = fit.cpu()
    for _ in range(iterations):  # the sums on the CPU: a GPU's index_add_ adds in no fixed order
        labels = assign(fit).cpu()
        count = torch.zeros(k).index_add_(0, labels, torch.ones(len(fit)))
        total = torch.zeros(k, X.shape[1]).index_add_(0, labels, fit_cpu)
        C = torch.where(count[:, None] > 0, total / count.clamp(min=1)[:, None], C.cpu()).to(dev)
    return C.cpu().numpy(), assign(X).cpu().numpy()


@functools.lru_cache(maxsize=4)
def permutation(n: int) -> torch.Tensor:
    """The k-means' random order of n rows (int64 [n] on the CPU; seeded, so the same in every call; kept for the
    last few n: a video's scenes share one n, and drawing it took 3 ms at 202,752 rows). Read only."""
    return torch.randperm(n, generator=torch.Generator().manual_seed(0))
