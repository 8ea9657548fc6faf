"""The frozen stereo encoder interface (SPEC section 7, "Encoder"; paper section 4.1 and appendix A).

An encoder maps a rectified pair (left, right) [B,3,H,W] in [0,1] to a left-reference disparity map
[B,1,H,W] in pixels of the input (positive = valid; d <= 0 means "unknown", which the model maps to
z_max) and a list of feature maps F^s [B,C_s,ceil(H/s),ceil(W/s)], one per downsampling factor s in
``feature_scales``. It is frozen: always in eval mode, no parameter requires a gradient, and
``train(mode)`` leaves it in eval mode, so a model that calls ``.train()`` on itself cannot switch its
batch-norm layers to batch statistics. Networks that need sizes divisible by some factor pad inside
``forward`` (``pad_to_multiple``) and crop their outputs back (``crop_to``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn


@dataclass
class EncoderOutput:
    """What an encoder returns.

    disparity: [B,1,H,W] float32, pixels of the input, left reference, positive = valid.
    features: [B,C_s,ceil(H/s),ceil(W/s)] float32 per scale, in the encoder's ``feature_scales`` order.
    """

    disparity: Tensor
    features: list[Tensor]


class StereoEncoder(nn.Module):
    """Base class of every frozen stereo encoder; subclasses set the class attributes and ``encode``.

    Attributes:
        name: registry name.
        feature_channels: C_s of each feature map, in the order of ``EncoderOutput.features``.
        feature_scales: downsampling factor s of each feature map.
        weights_sha256: sha256 of the loaded weights file; None for classical encoders.
    """

    name: str = ""
    feature_channels: tuple[int, ...] = ()
    feature_scales: tuple[int, ...] = ()
    weights_sha256: str | None = None

    def max_disparity(self, width: int) -> float:
        """The largest disparity (pixels) the encoder can report on images ``width`` pixels wide: the end of
        its search range, where a match may lie further (``geometry.disparity_validity`` keeps only
        disparities below it). Unbounded (inf) unless the subclass says."""
        return math.inf

    def freeze(self) -> StereoEncoder:
        """Eval mode and requires_grad False on every parameter; call at the end of ``__init__``."""
        for p in self.parameters():
            p.requires_grad_(False)
        return super().train(False)

    def train(self, mode: bool = True) -> StereoEncoder:
        """Frozen: stays in eval mode whatever ``mode`` is."""
        return super().train(False)

    def forward(self, left: Tensor, right: Tensor) -> EncoderOutput:
        check_pair(left, right)
        with torch.no_grad():
            out = self.encode(left, right)
        h, w = left.shape[-2:]
        for f, s, c in zip(out.features, self.feature_scales, self.feature_channels):
            expected = (left.shape[0], c, math.ceil(h / s), math.ceil(w / s))
            if tuple(f.shape) != expected:
                raise RuntimeError(f"{self.name}: feature at scale {s} has shape {tuple(f.shape)}, "
                                   f"expected {expected}")
        return out

    def encode(self, left: Tensor, right: Tensor) -> EncoderOutput:
        """(left, right) [B,3,H,W] in [0,1] -> EncoderOutput; called without gradients."""
        raise NotImplementedError


def check_pair(left: Tensor, right: Tensor) -> None:
    """Clear errors for a malformed stereo pair (shapes, dtype)."""
    for label, x in (("left", left), ("right", right)):
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"encoder input {label}: expected [B,3,H,W], got {tuple(x.shape)}")
        if not x.is_floating_point():
            raise ValueError(f"encoder input {label}: expected floating point in [0,1], got {x.dtype}")
    if left.shape != right.shape:
        raise ValueError(f"encoder inputs: left {tuple(left.shape)} and right {tuple(right.shape)} differ")


def pad_to_multiple(x: Tensor, multiple: int, min_size: int = 0) -> Tensor:
    """Pad [B,C,H,W] at the bottom and right by edge replication so that H and W are multiples of
    ``multiple`` and at least ``min_size``. Pixel (0, 0) stays in place, so disparities and features of
    the original pixels keep their coordinates; ``crop_to`` undoes it."""
    h, w = x.shape[-2:]
    ph = max(math.ceil(h / multiple) * multiple, math.ceil(min_size / multiple) * multiple) - h
    pw = max(math.ceil(w / multiple) * multiple, math.ceil(min_size / multiple) * multiple) - w
    if ph == 0 and pw == 0:
        return x
    return F.pad(x, (0, pw, 0, ph), mode="replicate")


def crop_to(x: Tensor, height: int, width: int, scale: int = 1) -> Tensor:
    """The top-left [.., ceil(height/scale), ceil(width/scale)] of a map computed on a padded input."""
    return x[..., : math.ceil(height / scale), : math.ceil(width / scale)]
