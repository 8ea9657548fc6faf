"""Stand-in for FoundationStereo's ``core/update.py``: the update block rewrites the ``net`` list it is given
(in place) and returns that same list, the mask features and the disparity update."""

import torch
import torch.nn.functional as F
from torch import nn

from tests.support.standin_foundation_stereo.standin_stereo import ConvGRU


def pool2x(x):
    return F.avg_pool2d(x, 3, stride=2, padding=1)


def interp(x, dest):
    return F.interpolate(x, dest.shape[2:], mode='bilinear', align_corners=True)


class BasicSelectiveMultiUpdateBlock(nn.Module):
    def __init__(self, args, hidden_dim=128, volume_dim=8):
        super().__init__()
        self.args = args
        n = args.n_gru_layers
        self.encoder = nn.Conv2d(2, hidden_dim, 3, padding=1)
        if n == 3:
            self.gru16 = ConvGRU(hidden_dim, hidden_dim * 2)
        if n >= 2:
            self.gru08 = ConvGRU(hidden_dim, hidden_dim * (n == 3) + hidden_dim * 2)
        self.gru04 = ConvGRU(hidden_dim, hidden_dim * (n > 1) + hidden_dim * 2)
        self.disp_head = nn.Conv2d(hidden_dim, 1, 3, padding=1)
        self.mask = nn.Conv2d(hidden_dim, 32, 3, padding=1)

    def forward(self, net, inp, corr, disp, att):
        n = self.args.n_gru_layers
        if n == 3:
            net[2] = self.gru16(att, net[2], inp[2], pool2x(net[1]))
        if n >= 2:
            net[1] = self.gru08(att, net[1], inp[1], pool2x(net[0]), *([interp(net[2], net[1])] if n > 2 else []))
        motion = torch.cat([inp[0], self.encoder(torch.cat([disp, corr], 1))], 1)
        net[0] = self.gru04(att, net[0], motion, *([interp(net[1], net[0])] if n > 1 else []))
        return net, 0.25 * self.mask(net[0]), self.disp_head(net[0])
