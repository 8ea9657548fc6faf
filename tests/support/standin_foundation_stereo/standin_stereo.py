"""Shared pieces of the FoundationStereo stand-ins (written for sgmodel's tests, no code of NVIDIA's): the input
check and ImageNet normalisation, a small backbone with the stage widths and strides of timm's ``edgenext_small``
(used when timm is not installed), an upsample-and-concatenate block, and an exact SAD block matcher for the
disparity (pixels, left reference)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
#: Output widths of edgenext_small's four stages (strides 4, 8, 16, 32), as both repositories hard-code them.
EDGENEXT_SMALL_CHANS = (48, 96, 160, 304)


def normalise(img: torch.Tensor) -> torch.Tensor:
    """[B,3,H,W] RGB in [0,255] -> ImageNet-normalised; rejects [0,1] inputs and unpadded sizes like a test should."""
    if img.shape[-2] % 32 or img.shape[-1] % 32:
        raise ValueError(f"stand-in: image size {tuple(img.shape[-2:])} is not a multiple of 32")
    if float(img.max()) <= 1.0:
        raise ValueError("stand-in: expects RGB in [0, 255]")
    return (img / 255.0 - MEAN.to(img)) / STD.to(img)


class TinyEdgeNext(nn.Module):
    """``stem`` (stride 4) and four ``stages`` (strides 1, 2, 2, 2) with edgenext_small's widths."""

    def __init__(self) -> None:
        super().__init__()
        c = EDGENEXT_SMALL_CHANS
        self.stem = nn.Conv2d(3, c[0], 4, 4)
        self.stages = nn.Sequential(nn.Conv2d(c[0], c[0], 3, 1, 1),
                                    *(nn.Conv2d(a, b, 2, 2) for a, b in zip(c[:-1], c[1:])))


class Conv2xUp(nn.Module):
    """Upsample ``x`` by 2 to ``out_channels``, concatenate the skip ``rem`` (same width): 2 * out_channels."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.up = nn.ConvTranspose2d(in_channels, out_channels, 2, 2)

    def forward(self, x: torch.Tensor, rem: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.relu(self.up(x)), rem], 1)


def block_match(left: torch.Tensor, right: torch.Tensor, max_disp: int = 24, radius: int = 2) -> torch.Tensor:
    """[B,1,H,W] integer disparity minimising the 5x5 mean absolute difference (grey levels)."""
    gl, gr = left.mean(1, keepdim=True), right.mean(1, keepdim=True)
    costs = []
    for d in range(max_disp):
        shifted = F.pad(gr, (d, 0))[..., : gr.shape[-1]]
        costs.append(F.avg_pool2d((gl - shifted).abs(), 2 * radius + 1, 1, radius))
    return torch.stack(costs, 1).squeeze(2).argmin(1, keepdim=True).float()


class ConvGRU(nn.Module):
    """A one-convolution recurrent cell: h' = tanh(conv([h, *x])); the stand-ins' "selective GRU"."""

    def __init__(self, hidden_dim: int, input_dim: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(hidden_dim + input_dim, hidden_dim, 3, padding=1)

    def forward(self, att, h: torch.Tensor, *x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.conv(torch.cat([h, *x], 1)))


def correlation(left: torch.Tensor, right: torch.Tensor, levels: int) -> torch.Tensor:
    """[B,levels,H,W]: mean over channels of left * right shifted by d = 0..levels-1 pixels."""
    return torch.cat([(left * F.pad(right, (d, 0))[..., : right.shape[-1]]).mean(1, keepdim=True)
                      for d in range(levels)], 1)
