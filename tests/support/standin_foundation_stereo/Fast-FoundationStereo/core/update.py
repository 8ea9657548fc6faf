"""Stand-in for Fast-FoundationStereo's ``core/update.py``: one GRU level; the block rewrites ``net[0]`` in place
and returns the list. ``encoder.convc1`` is the layer their pruned release narrows."""

import torch
from torch import nn

from tests.support.standin_foundation_stereo.standin_stereo import ConvGRU


class BasicMotionEncoder(nn.Module):
    def __init__(self, args, volume_dim=8):
        super().__init__()
        corr_planes = args.corr_levels * (2 * args.corr_radius + 1)
        self.convc1 = nn.Conv2d(corr_planes, 64, 1)
        self.convd1 = nn.Conv2d(1, 16, 3, padding=1)
        self.conv = nn.Conv2d(64 + 16, args.hidden_dims[0] - 1, 3, padding=1)

    def forward(self, disp, corr):
        out = torch.relu(self.conv(torch.cat([torch.relu(self.convc1(corr)), torch.relu(self.convd1(disp))], 1)))
        return torch.cat([out, disp], dim=1)


class BasicSelectiveMultiUpdateBlock(nn.Module):
    def __init__(self, args, hidden_dim=128, volume_dim=8):
        super().__init__()
        self.args = args
        self.encoder = BasicMotionEncoder(args, volume_dim)
        self.gru04 = ConvGRU(hidden_dim, hidden_dim * 2)
        self.disp_head = nn.Conv2d(hidden_dim, 1, 3, padding=1)
        self.mask = nn.Conv2d(hidden_dim, 32, 3, padding=1)

    def forward(self, net, inp, corr, disp, att):
        motion_features = torch.cat([inp[0], self.encoder(disp, corr)], dim=1)
        net[0] = self.gru04(att, net[0], motion_features)
        return net, .25 * self.mask(net[0]), self.disp_head(net[0])
