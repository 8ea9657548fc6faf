"""The Gaussian predictor H on the canvas (paper eq. 2, appendix A "Dense predictor and canvas").

A shared regressor (conv3x3 -> GELU -> conv3x3) maps [RGB~, z~, Phi~] to h (C channels). Three branches
read [h, RGB~, Phi~], each conv3x3 -> GroupNorm -> GELU -> conv3x3: front (37 channels), back (37) and
dz (1). All convolutions pad by replication. Ablations drop inputs: ``descriptor=False`` removes Phi~,
``rgbd=False`` removes RGB~ and z~ (the composer still uses them as anchors).

The branches read the same input, so their first layers run as one: the shared input is convolved once
with the branches' first-conv weights stacked (3C outputs) and normalised by one GroupNorm of 3x the
groups (groups are contiguous channel blocks, so this is exactly each branch's own GroupNorm), whose output
comes as one tensor per branch (``layers.group_norm_gelu_parts``) for the branch's final conv. The
parameters stay per branch (``front``, ``back``, ``dz``): the same state_dict and the same function as
three separate branches, with one read of the wide input instead of three.

Output channels of the front/back branches (SPEC section 7), named in ``composer.CHANNELS``; the final convs
start at exactly zero for scale, SH and the whole dz branch, and small and non-zero for opacity, offset
and quaternion (ml-sharp's zero-initialised heads, with the paper's exception).
"""

from __future__ import annotations

import torch
from torch import nn

from sgmodel.config import ConfigurationError, PredictorParams
from sgmodel.model.composer import CHANNELS, LAYER_CHANNELS
from sgmodel.model.layers import (GroupNorm, ReplicateConv2d, activation_format, cat_channels, compute_dtype,
                                  group_norm_gelu_parts, input_multiple, output_multiple, replicate_conv3x3)

ZERO_INIT = ("scale", "sh")  # exactly zero at initialisation (appendix A)


def _conv3(cin: int, cout: int) -> ReplicateConv2d:
    return ReplicateConv2d(cin, cout)


class Branch(nn.Sequential):
    """conv3x3 -> GroupNorm -> GELU -> conv3x3 (the norm and the activation fused on CUDA)."""

    def __init__(self, cin: int, hidden: int, cout: int, groups: int) -> None:
        super().__init__(_conv3(cin, hidden), GroupNorm(groups, hidden), nn.GELU(), _conv3(hidden, cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return fused_branches([self], x)[0]

    @property
    def first(self) -> nn.Conv2d:
        return self[0]

    @property
    def norm(self) -> GroupNorm:
        return self[1]

    @property
    def final(self) -> nn.Conv2d:
        return self[-1]


def fused_branches(branches: list[Branch], x: torch.Tensor) -> list[torch.Tensor]:
    """Every branch applied to the same input ``x`` [B,Cin',H,W] (Cin' >= Cin: zero channels beyond the
    branches' inputs, ``layers.cat_channels``), first layers as one (module docstring)."""
    firsts, norms = [b.first for b in branches], [b.norm for b in branches]
    if len({(c.out_channels, n.num_groups) for c, n in zip(firsts, norms)}) != 1:
        raise ValueError("fused branches need the same hidden width and groups")
    hidden = replicate_conv3x3(x, torch.cat([c.weight for c in firsts]), torch.cat([c.bias for c in firsts]),
                               output_multiple(x))
    hidden = group_norm_gelu_parts(hidden, sum(n.num_groups for n in norms), torch.cat([n.weight for n in norms]),
                                   torch.cat([n.bias for n in norms]), norms[0].eps, parts=len(branches))
    return [b.final(h) for b, h in zip(branches, hidden)]


class GaussianPredictor(nn.Module):
    """(front [B,37,Hc,Wc], back [B,37,Hc,Wc], dz [B,1,Hc,Wc]) = H([RGB~, z~, Phi~])."""

    def __init__(self, params: PredictorParams, descriptor_channels: int, rgbd: bool, back_layer: bool = True) -> None:
        super().__init__()
        self.rgbd = rgbd
        self.use_descriptor = descriptor_channels > 0
        if not rgbd and not self.use_descriptor:
            raise ConfigurationError("the predictor needs RGB-D or the descriptor as input")
        C = params.channels
        cin = (4 if rgbd else 0) + descriptor_channels
        branch_in = C + (3 if rgbd else 0) + descriptor_channels
        self.regressor = nn.Sequential(_conv3(cin, C), nn.GELU(), _conv3(C, C))
        self.front = Branch(branch_in, C, LAYER_CHANNELS, params.groups)
        # without a back layer there is nothing to predict for it: no back or dz branch at all
        self.back = Branch(branch_in, C, LAYER_CHANNELS, params.groups) if back_layer else None
        self.dz = Branch(branch_in, C, 1, params.groups) if back_layer else None
        self._init_layer_head(self.front.final, params.init_std)
        if back_layer:
            self._init_layer_head(self.back.final, params.init_std)
            nn.init.zeros_(self.dz.final.weight)
            nn.init.zeros_(self.dz.final.bias)

    @staticmethod
    def _init_layer_head(conv: nn.Conv2d, std: float) -> None:
        with torch.no_grad():
            nn.init.normal_(conv.weight, std=std)
            nn.init.zeros_(conv.bias)
            for name in ZERO_INIT:
                conv.weight[CHANNELS[name]] = 0.0

    def forward(self, rgb: torch.Tensor, z: torch.Tensor, phi: torch.Tensor | None, phi_padding: int = 0,
                phi_bias: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Canvas inputs rgb [B,3,Hc,Wc] in [0,1], z [B,1,Hc,Wc] metres, phi [B,C,Hc - 2p,Wc - 2p] or None,
        p = ``phi_padding``: phi is edge-replicated onto the canvas by the concatenations that read it
        (``layers.cat_channels``), with no padded copy of its own; ``phi_bias`` [C]: a bias those concatenations
        add to phi as they copy it (the decoder's last, ``DPTDecoder.without_last_bias``), or None. back and dz
        are None without a back layer. Activations in ``layers.activation_format``; the concatenated inputs
        carry zero channels up to ``layers.input_multiple``. The regressor's last bias is likewise added by the
        concatenation that copies h (on CUDA: in the copy, not in a pass over h of its own)."""
        dtype, fmt = compute_dtype(rgb.device), activation_format(rgb)  # cast once, in the convolutions' dtype
        rgb, z = rgb.to(dtype, memory_format=fmt), z.to(dtype, memory_format=fmt)
        phi = None if phi is None else phi.to(dtype, memory_format=fmt)
        multiple = input_multiple(rgb)
        desc, desc_bias = ([phi], [phi_bias]) if self.use_descriptor else ([], [])

        def on_canvas(tensors: list[torch.Tensor], biases: list[torch.Tensor | None]) -> torch.Tensor:
            return cat_channels(tensors, multiple, [phi_padding if t is phi else 0 for t in tensors], biases)

        first, gelu, last = self.regressor
        rgbd = [rgb, z] if self.rgbd else []
        h = gelu(first(on_canvas(rgbd + desc, [None] * len(rgbd) + desc_bias)))
        h = replicate_conv3x3(h, last.weight, None, output_multiple(h))  # its bias: in the concatenation below
        colour = rgbd[:1]  # the branches read RGB~, not z~
        shared = on_canvas([h, *colour, *desc], [last.bias, *[None] * len(colour), *desc_bias])
        if self.back is None:
            return self.front(shared), None, None
        front, back, dz = fused_branches([self.front, self.back, self.dz], shared)  # the same as each alone
        return front, back, dz
