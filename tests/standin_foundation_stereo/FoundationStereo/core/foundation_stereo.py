"""Stand-in for NVlabs/FoundationStereo's ``core/foundation_stereo.py`` (see ../../README.md)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from standin_foundation_stereo.standin_stereo import Pyramid, block_match, normalise


class Feature(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.pyramid = Pyramid()
        self.d_out = self.pyramid.d_out

    def forward(self, x):
        out = self.pyramid(x)
        return out, out[-1]  # (features at 1/4..1/32, "ViT" features)


class ContextNetDino(nn.Module):
    """(hidden, context) pairs per GRU level at 1/4, 1/8, 1/16."""

    def __init__(self, args):
        super().__init__()
        self.levels = nn.ModuleList(nn.Conv2d(3, 2 * h, 3, 4 * 2 ** i, 1) for i, h in enumerate(args.hidden_dims))

    def forward(self, image, vit_feat=None, num_layers=3):
        return [tuple(conv(image).chunk(2, 1)) for conv in self.levels[:num_layers]]


class BasicSelectiveMultiUpdateBlock(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.mix = nn.ModuleList(nn.Conv2d(h, h, 1) for h in args.hidden_dims)
        self.calls = 0

    def forward(self, net_list, inp_list, geo_feat, disp, att):
        self.calls += 1
        net_list = [torch.tanh(n + m(i)) for n, i, m in zip(net_list, inp_list, self.mix)]
        return net_list, net_list[0], torch.zeros_like(disp)


class FoundationStereo(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.args = args
        self.feature = Feature(args)
        self.cnet = ContextNetDino(args)
        self.update_block = BasicSelectiveMultiUpdateBlock(args)

    def forward(self, image1, image2, iters=12, flow_init=None, test_mode=False, low_memory=False, init_disp=None):
        b = len(image1)
        image1, image2 = normalise(image1), normalise(image2)
        out, _ = self.feature(torch.cat([image1, image2], 0))
        cnet = self.cnet(image1, vit_feat=None, num_layers=self.args.n_gru_layers)
        net_list = [torch.tanh(x[0]) for x in cnet]
        inp_list = [torch.relu(x[1]) for x in cnet]
        disp = F.avg_pool2d(block_match(image1, image2), 4) / 4
        for _ in range(iters):
            net_list, _, delta = self.update_block(net_list, inp_list, None, disp, None)
            disp = disp + delta
        full = block_match(image1, image2)
        return full if test_mode else (disp, [full])
