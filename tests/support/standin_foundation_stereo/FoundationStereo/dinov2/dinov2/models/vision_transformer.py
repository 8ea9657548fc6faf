"""Stand-in for DINOv2's vision transformer: 14-pixel patches and one attention block, ``blocks[0].attn.qkv``."""

import torch
from torch import nn


class Attention(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.qkv = nn.Linear(dim, 3 * dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = self.qkv(x).chunk(3, -1)
        return torch.softmax(q @ k.transpose(1, 2) / q.shape[-1] ** 0.5, -1) @ v


class Block(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.attn = Attention(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.attn(x)


class DinoVisionTransformer(nn.Module):
    patch_size = 14

    def __init__(self, embed_dim: int) -> None:
        super().__init__()
        self.patch_embed = nn.Conv2d(3, embed_dim, self.patch_size, self.patch_size)
        self.blocks = nn.ModuleList([Block(embed_dim)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """[B,3,H,W] (multiples of 14) -> patch features [B,D,H/14,W/14]."""
        t = self.patch_embed(x)
        b, d, h, w = t.shape
        tokens = t.flatten(2).transpose(1, 2)
        for block in self.blocks:
            tokens = block(tokens)
        return tokens.transpose(1, 2).reshape(b, d, h, w)
