"""Shared pieces of the FoundationStereo stand-ins: input check, normalisation, a small 4-scale feature
pyramid and an exact SAD block matcher for disparity (pixels, left reference)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def normalise(img: torch.Tensor) -> torch.Tensor:
    """[B,3,H,W] RGB in [0,255] -> ImageNet-normalised; rejects [0,1] inputs like a test should."""
    if img.shape[-2] % 32 or img.shape[-1] % 32:
        raise ValueError(f"stand-in: image size {tuple(img.shape[-2:])} is not a multiple of 32")
    if float(img.max()) <= 1.0:
        raise ValueError("stand-in: expects RGB in [0, 255]")
    return (img / 255.0 - MEAN) / STD


class Pyramid(nn.Module):
    """Four maps at 1/4, 1/8, 1/16, 1/32 with ``d_out`` channels."""

    def __init__(self, d_out=(8, 12, 16, 20)):
        super().__init__()
        self.d_out = list(d_out)
        cin = [3, *d_out[:-1]]
        self.convs = nn.ModuleList(nn.Conv2d(a, b, 3, 4 if i == 0 else 2, 1) for i, (a, b) in enumerate(zip(cin, d_out)))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for conv in self.convs:
            x = torch.relu(conv(x))
            out.append(x)
        return out


def block_match(left: torch.Tensor, right: torch.Tensor, max_disp: int = 24, radius: int = 2) -> torch.Tensor:
    """[B,1,H,W] integer disparity minimising the 5x5 mean absolute difference (grey levels)."""
    gl, gr = left.mean(1, keepdim=True), right.mean(1, keepdim=True)
    costs = []
    for d in range(max_disp):
        shifted = F.pad(gr, (d, 0))[..., : gr.shape[-1]]
        costs.append(F.avg_pool2d((gl - shifted).abs(), 2 * radius + 1, 1, radius))
    return torch.stack(costs, 1).squeeze(2).argmin(1, keepdim=True).float()
