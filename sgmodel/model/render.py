"""Rendering of the Gaussians dict: the only sgmodel module that calls the project's rasteriser.

The Gaussians dict (contracts "Gaussians"): means [B,N,3] metres in the left camera frame, quats [B,N,4]
wxyz, scales [B,N,3] metres (linear), opacities [B,N] in [0,1], sh [B,N,9,3] SH degree 2 coefficients
(colour = max(SH(d) + 0.5, 0)). SH degree 2 only: plain-colour Gaussians are not accepted (a plain colour
c is SH DC (c - 0.5) / C0 with the higher coefficients zero).
"""

from __future__ import annotations

import torch

from scenesplat_stereo.raster import rasterization, tile_size_for

#: SH degree of every Gaussian the model predicts (SPEC section 7 "Rendering").
SH_DEGREE = 2
#: Number of SH coefficients per colour channel at SH_DEGREE.
SH_COEFFS = (SH_DEGREE + 1) ** 2
#: Keys of the Gaussians dict.
GAUSSIAN_KEYS = ("means", "quats", "scales", "opacities", "sh")


def check_gaussians(gaussians: dict) -> tuple[int, int]:
    """Raise ValueError naming the field when ``gaussians`` does not follow the contract; returns (B, N)."""
    missing = [k for k in GAUSSIAN_KEYS if k not in gaussians]
    if missing:
        raise ValueError(f"gaussians: missing fields {missing} (expected {list(GAUSSIAN_KEYS)})")
    means = gaussians["means"]
    if means.ndim != 3 or means.shape[2] != 3:
        raise ValueError(f"gaussians['means'] must be [B, N, 3], got {tuple(means.shape)}")
    b, n = means.shape[:2]
    shapes = {"quats": (b, n, 4), "scales": (b, n, 3), "opacities": (b, n), "sh": (b, n, SH_COEFFS, 3)}
    for key, shape in shapes.items():
        if tuple(gaussians[key].shape) != shape:
            raise ValueError(f"gaussians[{key!r}] must be {list(shape)} (SH degree {SH_DEGREE}), "
                             f"got {list(gaussians[key].shape)}")
    return b, n


def render_views(gaussians: dict, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                 backgrounds: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Render each scene of the batch into its T cameras, SH degree 2, in the rasteriser's default "classic"
    mode (SPEC section 7 names no other; in "antialiased" mode a grid of pixel-footprint Gaussians covers a
    surface to alpha 0.83 only, tests/sgmodel/model/test_baselines.py).

    viewmats [B,T,4,4] world(= left camera)-to-target; Ks [B,T,3,3] pixels; backgrounds [B,T,3] or None
    (black). Returns rgb [B,T,3,H,W] (not clipped) and alpha [B,T,1,H,W], differentiable.
    """
    b, _ = check_gaussians(gaussians)
    if viewmats.ndim != 4 or viewmats.shape[0] != b or viewmats.shape[2:] != (4, 4):
        raise ValueError(f"viewmats must be [B={b}, T, 4, 4], got {tuple(viewmats.shape)}")
    t = viewmats.shape[1]
    if tuple(Ks.shape) != (b, t, 3, 3):
        raise ValueError(f"Ks must be [{b}, {t}, 3, 3], got {tuple(Ks.shape)}")
    if backgrounds is not None and tuple(backgrounds.shape) != (b, t, 3):
        raise ValueError(f"backgrounds must be [{b}, {t}, 3], got {tuple(backgrounds.shape)}")
    rgb, alpha, _ = rasterization(
        gaussians["means"], gaussians["quats"], gaussians["scales"], gaussians["opacities"], gaussians["sh"],
        viewmats, Ks, int(width), int(height), sh_degree=SH_DEGREE, backgrounds=backgrounds,
        tile_size=tile_size_for(str(viewmats.device)))              # one call for the batch: [B,T,H,W,C]
    return rgb.permute(0, 1, 4, 2, 3), alpha.permute(0, 1, 4, 2, 3)
