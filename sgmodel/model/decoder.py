"""The DPT decoder D: frozen stereo features plus RGB-D -> a dense descriptor Phi (paper eq. 1, appendix A).

Per scale s (the encoder's feature scales, or ``DecoderParams.rgbd_scales`` for an encoder without
features): concat [F^s, RGB resized bilinearly to H/s, depth z resized nearest to H/s] -> 1x1 conv ->
GroupNorm -> GELU -> C channels. Then DPT's coarse-to-fine fusion: starting at the coarsest scale, each
level is a residual conv unit of its projection plus the bilinearly upsampled fused coarser level, and a
second residual conv unit; the finest level is upsampled to H x W and refined by a 3x3 conv -> GELU ->
1x1 conv. Output Phi [B, C, H, W] at the original resolution (the canvas is padded afterwards).

Depth enters in metres (0.1..10, as the composer uses it); RGB in [0, 1]. ``rgbd=False`` drops RGB and
depth from every scale (Table 4 "without RGB-D conditioning"), keeping the encoder features.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sgmodel.config import ConfigurationError
from sgmodel.model.layers import GroupNorm, activation_format, cat_channels, compute_dtype, conv_gelu, upsample_bilinear


class ResidualConvUnit(nn.Module):
    """x + conv3x3(GELU(conv3x3(GELU(x)))), DPT's refinement unit (the first conv's bias added with the GELU
    after it, ``layers.conv_gelu``)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(conv_gelu(self.conv1, F.gelu(x)))


class FusionBlock(nn.Module):
    """One level of coarse-to-fine fusion: RCU(projection) + upsampled coarser level, then RCU."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.skip = ResidualConvUnit(channels)
        self.out = ResidualConvUnit(channels)

    def forward(self, x: torch.Tensor, coarser: torch.Tensor | None) -> torch.Tensor:
        x = self.skip(x)
        if coarser is not None:
            x = x + F.interpolate(coarser, size=x.shape[-2:], mode="bilinear", align_corners=False)
        return self.out(x)


class Projection(nn.Sequential):
    """1x1 conv -> GroupNorm -> GELU (the norm and the activation fused on CUDA, ``GroupNorm.gelu_after``)."""

    def __init__(self, cin: int, channels: int, groups: int) -> None:
        super().__init__(nn.Conv2d(cin, channels, 1), GroupNorm(groups, channels), nn.GELU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self[1].gelu_after(self[0](x))


def _scaled_size(height: int, width: int, s: int) -> tuple[int, int]:
    return -(-height // s), -(-width // s)


class DPTDecoder(nn.Module):
    """Phi = D({[F^s, down_s I_L, down_s z]}_s).

    Args:
        feature_channels: C_s of each encoder feature map (empty for an encoder without features).
        feature_scales: s of each map (same order); ``rgbd_scales`` is used when there are none.
        channels: width C of Phi. groups: GroupNorm groups. rgbd: concat RGB and depth per scale.
    """

    def __init__(self, feature_channels: tuple[int, ...], feature_scales: tuple[int, ...], channels: int,
                 groups: int, rgbd: bool, rgbd_scales: tuple[int, ...]) -> None:
        super().__init__()
        if len(feature_channels) != len(feature_scales):
            raise ValueError("one scale per encoder feature map")
        if not feature_channels:
            if not rgbd:
                raise ConfigurationError("an encoder without features needs RGB-D conditioning (rgbd=True)")
            feature_channels, feature_scales = (0,) * len(rgbd_scales), tuple(rgbd_scales)
        extra = 4 if rgbd else 0
        order = sorted(range(len(feature_scales)), key=lambda i: -feature_scales[i])  # coarse to fine
        self.order = order
        self.scales = tuple(feature_scales)
        self.rgbd = rgbd
        self.project = nn.ModuleList(Projection(c + extra, channels, groups) for c in feature_channels)
        self.fuse = nn.ModuleList(FusionBlock(channels) for _ in feature_channels)
        self.head = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1), nn.GELU(),
                                  nn.Conv2d(channels, channels, 1))

    def forward(self, features: list[torch.Tensor], rgb: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """features as the encoder gives them; rgb [B,3,H,W] in [0,1]; z [B,1,H,W] metres -> [B,C,H,W] (in
        ``layers.activation_format``: channels-last on CUDA)."""
        return self.head[2](conv_gelu(self.head[0], self._head_input(features, rgb, z)))

    def without_last_bias(self, features: list[torch.Tensor], rgb: torch.Tensor, z: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor]:
        """(Phi as ``forward`` gives it but for the head's last bias, that bias [C]): for a consumer that adds it as
        it copies Phi (``GaussianPredictor``'s concatenations), instead of a pass over Phi of its own."""
        last = self.head[2]
        return F.conv2d(conv_gelu(self.head[0], self._head_input(features, rgb, z)), last.weight), last.bias

    def _head_input(self, features: list[torch.Tensor], rgb: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """The coarse-to-fine fusion upsampled to H x W: the head's input, in the head's dtype."""
        H, W = rgb.shape[-2:]
        dtype, fmt = compute_dtype(rgb.device), activation_format(rgb)  # cast once, in the convolutions' dtype
        rgb, z = rgb.to(dtype, memory_format=fmt), z.to(dtype, memory_format=fmt)
        fused = None
        for i in self.order:
            size = features[i].shape[-2:] if features else _scaled_size(H, W, self.scales[i])
            parts = [features[i].to(dtype, memory_format=fmt)] if features else []
            if self.rgbd:  # resized in float32 under autocast, cast as the convolution would cast them
                parts += [F.interpolate(rgb, size=size, mode="bilinear", align_corners=False, antialias=True).to(dtype),
                          F.interpolate(z, size=size, mode="nearest").to(dtype)]
            fused = self.fuse[i](self.project[i](cat_channels(parts)), fused)
        return upsample_bilinear(fused, (H, W), dtype)  # head = conv3x3, GELU, conv1x1
