"""Building blocks shared by the decoder, the canvas and the predictor, written for a fast bf16 step.

- ``replicate_pad``: edge replication (each padded pixel copies the nearest border pixel) with a
  backward that sums the padded border into the edge pixels in a few slice operations. PyTorch's own
  ``replication_pad2d_backward`` scatters with atomics and was the largest single cost of a training step
  on an H100 (40 ms of 400 at 256x256, batch 32); this one is a copy of the gradient plus border sums.
- ``replicate_conv3x3`` / ``ReplicateConv2d``: a 3x3 convolution of the replicate-padded input (the
  predictor's convolutions) without the padded copy: a zero-padded convolution plus the ring's
  difference, whose gradients are added into the convolution's in place. Same parameters and state_dict
  keys as ``nn.Conv2d(..., padding=1, padding_mode="replicate")``.
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


def _ring_terms(top_row: torch.Tensor, bottom_row: torch.Tensor, left_col: torch.Tensor, right_col: torch.Tensor,
                weight: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """What edge replication adds to a zero-padded 3x3 convolution, per border of the output: the top
    row (``x[:, :, 0]`` replicated in width) meets the kernel's first row, the bottom row its last; the
    left and right columns (zero-padded in height, so that each corner is counted once, by its row) meet
    the kernel's first and last columns. Rows [B,Cin,W] -> [B,Cout,W]; columns [B,Cin,H] -> [B,Cout,H]."""
    return (F.conv1d(F.pad(top_row, (1, 1), mode="replicate"), weight[:, :, 0, :]),
            F.conv1d(F.pad(bottom_row, (1, 1), mode="replicate"), weight[:, :, 2, :]),
            F.conv1d(left_col, weight[:, :, :, 0], padding=1),
            F.conv1d(right_col, weight[:, :, :, 2], padding=1))


def _ring_inputs(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
    return x[:, :, 0, :], x[:, :, -1, :], x[:, :, :, 0], x[:, :, :, -1]


class _ReplicateConv3x3(torch.autograd.Function):
    """Zero-padded convolution plus the ring's difference, with a backward that adds the ring's small
    gradients into the convolution's own gradients in place. Left to autograd, each of the four border
    slices of ``x`` would cost a zero-filled gradient of ``x``'s full size and its addition (about 25 ms
    of a 330 ms training step at the predictor's sizes). Inputs share one dtype; autocast is off inside."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        with torch.autocast(x.device.type, enabled=False):
            out = F.conv2d(x, weight, bias, padding=1)
            top, bottom, left, right = _ring_terms(*_ring_inputs(x), weight)
            out[:, :, 0, :] += top
            out[:, :, -1, :] += bottom
            out[:, :, :, 0] += left
            out[:, :, :, -1] += right
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight = ctx.saved_tensors
        need_x, need_w, need_b = ctx.needs_input_grad
        with torch.autocast(grad.device.type, enabled=False):
            gx, gw, gb = torch.ops.aten.convolution_backward(
                grad, x, weight, [weight.shape[0]] if ctx.has_bias else None, [1, 1], [1, 1], [1, 1], False,
                [0, 0], 1, [need_x, need_w, need_b and ctx.has_bias])
            if need_x or need_w:
                with torch.enable_grad():
                    ring = [t.detach().requires_grad_(need_x) for t in _ring_inputs(x)]
                    w = weight.detach().requires_grad_(need_w)
                    wrt = (ring if need_x else []) + ([w] if need_w else [])
                    grads = torch.autograd.grad(_ring_terms(*ring, w), wrt, _ring_inputs(grad))
                if need_x:
                    for view, g in zip(_ring_inputs(gx), grads[:4]):
                        view += g  # in place: the corners get their row's and their column's share
                if need_w:
                    gw += grads[-1]
        return gx, gw, gb


def replicate_conv3x3(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """3x3 convolution of ``x`` [B,Cin,H,W] padded by one pixel of edge replication -> [B,Cout,H,W].

    Computed as cuDNN's zero-padded convolution (which pads inside the kernel, without a padded copy of
    the input) plus the difference replication makes, which lives on the one-pixel ring only
    (``_ring_terms``). Under autocast it runs in autocast's dtype, as ``F.conv2d`` would; else in ``x``'s."""
    dtype = torch.get_autocast_dtype(x.device.type) if torch.is_autocast_enabled(x.device.type) else x.dtype
    return _ReplicateConv3x3.apply(x.to(dtype), weight.to(dtype), None if bias is None else bias.to(dtype))


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
