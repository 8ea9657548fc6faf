"""The SOG writer's texels (``sog.encode_sog``), quantised in torch in the scene's order: on the GPU where there is
one, else on the CPU's intra-op threads (neither holds the GIL, so the writer's other threads run beside them).

On a GPU the scene's arrays are copied there (14 floats a Gaussian at SH 0) and the texels back (20 bytes a
Gaussian), and the work between is some 40 kernels; the numbers are the same on either device. Every step is
an IEEE operation in the precision written (float32 norms of the quaternions, the rest in float64) but the
logarithms (``log1p`` of the positions, ``log`` of the scales), which the devices' libraries round within an
ulp of each other: the box of t (``meta.json``) can differ by an ulp between devices, and a texel only where
such a value lies within an ulp of a rounding or codebook boundary.

The quantities (the format: ``sog``'s docstring): t = sign(x) ln(|x| + 1) of the positions (metres in, unitless
out) as 16-bit steps of their box, the quaternions' "smallest three" bytes, the opacity byte, and the nearest
entries of the log-scale and colour codebooks (``palettes``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from scenesplat_stereo.scene import palettes
from scenesplat_stereo.scene.gaussians import GaussianScene


def placed(scene: GaussianScene, dev: torch.device) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uint8 [3, N, 4] texels of ``means_l``, ``means_u`` and ``quats``, the box of t: mins [3], maxs [3]
    float64) of ``scene``, computed on ``dev`` (module docstring)."""
    means = _put(scene.means.T, dev).double()  # [3, N]: reductions along rows
    rgba = torch.empty((3, len(scene), 4), dtype=torch.uint8, device=dev)
    t = torch.sign(means) * torch.log1p(means.abs())
    mins, maxs = t.amin(1, keepdim=True), t.amax(1, keepdim=True)
    q = torch.round(65535.0 * (t - mins) / torch.where(maxs > mins, maxs - mins, 1.0)).int().T
    rgba[0, :, :3], rgba[1, :, :3], rgba[:2, :, 3] = q & 255, q >> 8, 255
    rgba[2] = pack_quats(_put(scene.quats, dev))
    return rgba.cpu().numpy(), mins[:, 0].cpu().numpy(), maxs[:, 0].cpu().numpy()


def scale_texels(scene: GaussianScene, dev: torch.device) -> tuple[np.ndarray, np.ndarray]:
    """(uint8 [N, 4] texels of ``scales``, the log-scale codebook [256] float32) of ``scene``, on ``dev``."""
    log_scales = torch.log(_put(scene.scales, dev).double())
    book = palettes.Nearest(palettes.codebook(log_scales), dev)
    rgba = torch.full((len(scene), 4), 255, dtype=torch.uint8, device=dev)
    rgba[:, :3] = book(log_scales)
    return rgba.cpu().numpy(), book.book


def colour_texels(scene: GaussianScene, dev: torch.device) -> tuple[np.ndarray, np.ndarray]:
    """(uint8 [N, 4] texels of ``sh0``: the colour codebook's entries and the opacity byte, the colour codebook
    [256] float32) of ``scene``, on ``dev``."""
    dc = _put(scene.sh[:, 0], dev).double()
    book = palettes.Nearest(palettes.codebook(dc), dev)
    rgba = torch.empty((len(scene), 4), dtype=torch.uint8, device=dev)
    rgba[:, :3] = book(dc)
    rgba[:, 3] = torch.round(_put(scene.opacities, dev).double() * 255.0).clamp_(0, 255)
    return rgba.cpu().numpy(), book.book


def _put(a: np.ndarray, dev: torch.device) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a)).to(dev)


def pack_quats(quats: torch.Tensor) -> torch.Tensor:
    """uint8 [m, 4] "smallest three" texels of unit wxyz quaternions [m, 4] float32: q / |q| (the norm in float32,
    ((w^2 + x^2) + y^2) + z^2 as numpy's row norm sums them) negated where its largest |component| (the first of
    equals) is negative; RGB the other three as rint(255 (sqrt(2) c / 2 + 1/2)), A = 252 + the largest's index."""
    q32 = quats.T  # [4, m]: one row per component
    square = q32 * q32
    q = q32.double() / torch.sqrt(((square[0] + square[1]) + square[2]) + square[3]).double()
    a = q.abs()
    first, second = (a[1] > a[0]).to(torch.uint8), (a[3] > a[2]).to(torch.uint8) + 2
    largest = torch.where(torch.maximum(a[2], a[3]) > torch.maximum(a[0], a[1]), second, first)
    value = q.gather(0, largest[None].long())[0]
    q *= torch.where(value < 0, -1.0, 1.0)  # exact as float32, and then by sqrt(2) in float64: as by +-sqrt(2)
    q *= math.sqrt(2.0)
    out = torch.empty((q.shape[1], 4), dtype=torch.uint8, device=q.device)
    for j in range(3):  # the j-th component other than the largest
        c = torch.where(largest <= j, q[j + 1], q[j])
        out[:, j] = torch.round((c * 0.5 + 0.5) * 255.0).clamp_(0, 255)
    out[:, 3] = 252 + largest
    return out


def sh_palette(sh: np.ndarray, degree: int, palette: int, dev: torch.device,
               stream: torch.cuda.Stream | None = None) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """The SH palette of ``sh`` [N, K, 3] (``sog``'s docstring): (its 256-entry codebook, the centroid image's
    texels, its rows, the label texels [N, 4] in the scene's order). The k-means runs on ``dev``, on ``stream``
    there (the caller's, when this runs in a pool task: else the device's default stream); the coefficients are
    put in its row order there too (numpy's strided copy took 7 ms at 202,752 Gaussians, SH 2)."""
    coeffs, n = (degree + 1) ** 2 - 1, len(sh)  # above the DC term: sog.SH_COEFFS (not imported: a circle)
    with torch.cuda.stream(stream):  # (None: as it is)
        rest = _put(sh, dev)[:, 1:].transpose(1, 2).reshape(n, 3 * coeffs)  # channel-major, as f_rest
        centroids, labels = palettes.kmeans(rest, palette, dev)
    book = palettes.codebook(centroids)
    cells = palettes.Nearest(book)(centroids).numpy().reshape(palette, 3, coeffs).transpose(0, 2, 1).reshape(-1, 3)
    rows = math.ceil(palette / 64)
    px = np.zeros((rows * 64 * coeffs, 4), np.uint8)
    px[:len(cells), :3], px[:, 3] = cells, 255
    texels = np.zeros((n, 4), np.uint8)
    texels[:, 0], texels[:, 1], texels[:, 3] = labels & 255, labels >> 8, 255
    return book, px, rows, texels
