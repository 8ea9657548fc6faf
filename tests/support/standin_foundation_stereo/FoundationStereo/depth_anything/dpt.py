"""Stand-in for FoundationStereo's ``depth_anything/dpt.py``: DINOv2 comes from torch.hub, as in the real one
(``torch.hub.load('facebookresearch/dinov2', ...)``, which needs GitHub unless it is served locally)."""

import torch
from torch import nn


class DepthAnything(nn.Module):
    def __init__(self, config):
        super().__init__()
        self.pretrained = torch.hub.load('facebookresearch/dinov2', 'dinov2_{:}14'.format(config['encoder']),
                                         pretrained=False)
        dim = self.pretrained.blocks[0].attn.qkv.in_features
        self.head = nn.Conv2d(dim, config['features'] // 2, 1)

    def forward(self, x):
        return self.head(self.pretrained(x))
