"""Stand-in for NVlabs/FoundationStereo's ``core/foundation_stereo.py`` (see ../../README.md). Its disparity is
the exact block matcher; the recurrent updates run for their hidden states."""

import os
import sys

import torch
import torch.nn.functional as F
from torch import nn

code_dir = os.path.dirname(os.path.realpath(__file__))
sys.path.append(f'{code_dir}/../')  # as the real module does
from core.extractor import ContextNetDino, Feature  # noqa: E402
from core.update import BasicSelectiveMultiUpdateBlock  # noqa: E402
from core.utils.utils import block_match, normalise  # noqa: E402


class FoundationStereo(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.args = args
        self.cnet = ContextNetDino(args, output_dim=[args.hidden_dims, args.hidden_dims], downsample=args.n_downsample)
        self.update_block = BasicSelectiveMultiUpdateBlock(self.args, self.args.hidden_dims[0])
        self.feature = Feature(args)
        self.proj_cmb = nn.Conv2d(self.feature.d_out[0], 1, 1)

    def forward(self, image1, image2, iters=12, flow_init=None, test_mode=False, low_memory=False, init_disp=None):
        B = len(image1)
        image1, image2 = normalise(image1), normalise(image2)
        out, vit_feat = self.feature(torch.cat([image1, image2], dim=0))
        full = block_match(image1, image2)
        disp = F.avg_pool2d(full, 4) / 4 if init_disp is None else init_disp
        cnet_list = list(self.cnet(image1, vit_feat=vit_feat[:B], num_layers=self.args.n_gru_layers))
        net_list = [torch.tanh(x[0]) for x in cnet_list]
        inp_list = [torch.relu(x[1]) for x in cnet_list]
        geo_feat = self.proj_cmb(out[0][:B])
        for _ in range(iters):
            net_list, mask_feat_4, delta_disp = self.update_block(net_list, inp_list, geo_feat, disp, None)
            disp = disp + delta_disp
        return full if test_mode else (disp, [full])
