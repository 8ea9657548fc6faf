"""Stand-in for NVlabs/Fast-FoundationStereo's ``core/foundation_stereo.py`` (see ../../README.md). Their
release pickles the whole ``FastFoundationStereo``; like the real module this one registers its package under a
second name (``foundation_stereo_ori``). Disparity: the exact block matcher; the updates run for their states."""

import os
import sys

import torch
import torch.nn.functional as F
from torch import nn

code_dir = os.path.dirname(os.path.realpath(__file__))
sys.path.append(f'{code_dir}/../')  # as the real module does
import Utils as U  # noqa: E402
from core.extractor import ContextNetSharedBackbone, Feature  # noqa: E402
from core.update import BasicSelectiveMultiUpdateBlock  # noqa: E402
from core.utils.utils import block_match, correlation, normalise  # noqa: E402

sys.modules['foundation_stereo_ori'] = sys.modules['core']


class FastFoundationStereo(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.args = args
        self.update_block = BasicSelectiveMultiUpdateBlock(self.args, self.args.hidden_dims[0])
        self.feature = Feature(args)
        self.proj_cmb = nn.Conv2d(self.feature.d_out[0], 12, kernel_size=1)
        self.cnet = ContextNetSharedBackbone(args, c04=self.feature.d_out[0], c08=self.feature.d_out[1],
                                             c16=self.feature.d_out[2], output_dim=[args.hidden_dims, args.hidden_dims])

    def forward(self, image1, image2, iters=12, test_mode=False, low_memory=False, init_disp=None, profile=False,
                optimize_build_volume='pytorch1'):
        if optimize_build_volume not in ('pytorch1', 'triton'):
            raise RuntimeError(f"Invalid optimize_build_volume: {optimize_build_volume}")
        B = len(image1)
        image1, image2 = normalise(image1), normalise(image2)
        with torch.amp.autocast('cuda', enabled=self.args.mixed_precision, dtype=U.AMP_DTYPE):
            out = self.feature(torch.cat([image1, image2], dim=0))
            features_left = [o[:B] for o in out]
            features_right = [o[B:] for o in out]
            corr = correlation(self.proj_cmb(features_left[0]), self.proj_cmb(features_right[0]),
                               self.args.corr_levels * (2 * self.args.corr_radius + 1))
            full = block_match(image1, image2)
            disp = F.avg_pool2d(full, 4) / 4 if init_disp is None else init_disp
            cnet_list = list(self.cnet(features_left[0], features_left[1], features_left[2]))
            net_list = [torch.tanh(x[0]) for x in cnet_list]
            inp_list = [torch.relu(x[1]) for x in cnet_list]
        for _ in range(iters):
            net_list, mask_feat_4, delta_disp = self.update_block(net_list, inp_list, corr, disp, None)
            disp = disp + delta_disp
        return full if test_mode else (disp, [full])
