"""Building blocks shared by the decoder, the canvas and the predictor, written for a fast bf16 step.

- ``replicate_pad``: edge replication (each padded pixel copies the nearest border pixel) with a
  backward that sums the padded border into the edge pixels in a few slice operations. PyTorch's own
  ``replication_pad2d_backward`` scatters with atomics and was the largest single cost of a training step
  on an H100 (40 ms of 400 at 256x256, batch 32); this one is a copy of the gradient plus border sums.
- ``replicate_conv3x3`` / ``ReplicateConv2d``: a 3x3 convolution of the replicate-padded input (the
  predictor's convolutions) without the padded copy: a zero-padded convolution plus the ring's
  difference. Same parameters and state_dict keys as ``nn.Conv2d(..., padding=1, padding_mode="replicate")``.
- ``GroupNorm``: ``nn.GroupNorm`` that keeps its input's dtype. Under autocast PyTorch runs GroupNorm in
  float32 (an up-cast copy in, a float32 tensor out and a down-cast before the next convolution); the
  CUDA kernel accumulates its statistics in float32 for bf16 inputs anyway, so running it in bf16 gives
  the same statistics with a third of the memory traffic. Same parameters and state_dict keys.
- ``compute_dtype``: the dtype convolutions run in here (autocast's, else float32), so that inputs are
  cast once before they are concatenated instead of concatenated in float32 and cast by every consumer.

On the CPU (no autocast) every block computes exactly what its PyTorch counterpart computes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class _ReplicatePad(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, p: int) -> torch.Tensor:
        ctx.p = p
        return F.pad(x, (p, p, p, p), mode="replicate")

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        p = ctx.p
        g = grad[..., p:-p, p:-p].clone()
        # edges (without corners): the padded rows/columns sum into the border row/column
        g[..., 0, :] += grad[..., :p, p:-p].sum(-2)
        g[..., -1, :] += grad[..., -p:, p:-p].sum(-2)
        g[..., :, 0] += grad[..., p:-p, :p].sum(-1)
        g[..., :, -1] += grad[..., p:-p, -p:].sum(-1)
        # corners: each p x p padded corner block sums into the corner pixel
        g[..., 0, 0] += grad[..., :p, :p].sum((-2, -1))
        g[..., 0, -1] += grad[..., :p, -p:].sum((-2, -1))
        g[..., -1, 0] += grad[..., -p:, :p].sum((-2, -1))
        g[..., -1, -1] += grad[..., -p:, -p:].sum((-2, -1))
        return g, None


def replicate_pad(x: torch.Tensor, p: int) -> torch.Tensor:
    """[B, C, H, W] (or [C, H, W]) -> [..., H + 2p, W + 2p] by edge replication; ``p = 0`` returns ``x``."""
    if p < 0:
        raise ValueError(f"padding must be >= 0, got {p}")
    return _ReplicatePad.apply(x, p) if p else x


class _AddRing(torch.autograd.Function):
    """out[:, :, 0] += top; out[:, :, -1] += bottom; out[..., 0] += left; out[..., -1] += right, in place.
    The backward hands the output gradient through and its border slices to the four terms: no copy of
    the (large) gradient, which autograd's in-place-on-a-view bookkeeping would make once per term."""

    @staticmethod
    def forward(ctx, out, top, bottom, left, right):
        out[:, :, 0, :] += top
        out[:, :, -1, :] += bottom
        out[:, :, :, 0] += left
        out[:, :, :, -1] += right
        ctx.mark_dirty(out)
        return out

    @staticmethod
    def backward(ctx, grad):
        return grad, grad[:, :, 0, :], grad[:, :, -1, :], grad[:, :, :, 0], grad[:, :, :, -1]


def replicate_conv3x3(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """3x3 convolution of ``x`` [B,Cin,H,W] padded by one pixel of edge replication -> [B,Cout,H,W].

    Computed as cuDNN's zero-padded convolution (which pads inside the kernel, without a padded copy of
    the input) plus the difference replication makes, which lives on the one-pixel ring only: the ring's
    top row (row 0 of ``x`` replicated in width) meets the kernel's first row and adds a 1D convolution of
    it to output row 0; likewise the bottom row, and the left and right columns (zero-padded in height,
    so that each corner of the ring is counted once, by its row)."""
    out = F.conv2d(x, weight, bias, padding=1)
    x = x.to(out.dtype)  # autocast casts the weights of each 1D convolution below alike
    top = F.conv1d(F.pad(x[:, :, 0, :], (1, 1), mode="replicate"), weight[:, :, 0, :])
    bottom = F.conv1d(F.pad(x[:, :, -1, :], (1, 1), mode="replicate"), weight[:, :, 2, :])
    left = F.conv1d(x[:, :, :, 0], weight[:, :, :, 0], padding=1)
    right = F.conv1d(x[:, :, :, -1], weight[:, :, :, 2], padding=1)
    return _AddRing.apply(out, *(t.to(out.dtype) for t in (top, bottom, left, right)))


class ReplicateConv2d(nn.Conv2d):
    """3x3 convolution of the input padded by edge replication to keep its size (``replicate_conv3x3``)."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(cin, cout, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return replicate_conv3x3(x, self.weight, self.bias)


def compute_dtype(device: torch.device) -> torch.dtype:
    """The dtype convolutions run in on ``device`` now: autocast's when it is on, else float32."""
    if torch.is_autocast_enabled(device.type):
        return torch.get_autocast_dtype(device.type)
    return torch.float32


def group_norm(x: torch.Tensor, groups: int, weight: torch.Tensor, bias: torch.Tensor, eps: float) -> torch.Tensor:
    """``F.group_norm`` in ``x``'s dtype (statistics accumulate in float32 on CUDA for bf16/fp16)."""
    with torch.autocast(x.device.type, enabled=False):
        return F.group_norm(x, groups, weight.to(x.dtype), bias.to(x.dtype), eps)


class GroupNorm(nn.GroupNorm):
    """``nn.GroupNorm`` that runs in its input's dtype (see the module docstring)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return group_norm(x, self.num_groups, self.weight, self.bias, self.eps)
