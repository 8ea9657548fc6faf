"""Stand-in for FoundationStereo's ``core/extractor.py``: ``Feature`` (edgenext_small from timm plus DINOv2
through ``depth_anything``) returns ``([x4, x8, x16, x32], vit_feat)``; ``ContextNetDino`` returns a tuple of
three ``[hidden, context]`` lists (1/4, 1/8, 1/16) whatever ``num_layers`` says, as the real ones do."""

import torch
import torch.nn.functional as F
from torch import nn

try:
    import timm  # the real module imports it unconditionally; sgmodel's CI has no timm
except ImportError:
    timm = None
from core.submodule import Conv2x_IN
from Utils import freeze_model, get_resize_keep_aspect_ratio

from tests.support.standin_foundation_stereo.standin_stereo import EDGENEXT_SMALL_CHANS, TinyEdgeNext


class DepthAnythingFeature(nn.Module):
    model_configs = {'vitl': {'encoder': 'vitl', 'features': 256}, 'vitb': {'encoder': 'vitb', 'features': 128},
                     'vits': {'encoder': 'vits', 'features': 64}}

    def __init__(self, encoder='vits'):
        super().__init__()
        from depth_anything.dpt import DepthAnything  # imported while the model is built, as in the real code
        self.encoder = encoder
        self.depth_anything = DepthAnything(self.model_configs[encoder])

    def forward(self, x):
        return {'out': self.depth_anything(x)}


class Feature(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.args = args
        model = timm.create_model('edgenext_small', pretrained=True, features_only=False) if timm else TinyEdgeNext()
        self.stem, self.stages = model.stem, model.stages
        chans = list(EDGENEXT_SMALL_CHANS)
        self.dino = freeze_model(DepthAnythingFeature(encoder=args.vit_size))
        vit_feat_dim = DepthAnythingFeature.model_configs[args.vit_size]['features'] // 2
        self.deconv32_16 = Conv2x_IN(chans[3], chans[2])
        self.deconv16_8 = Conv2x_IN(chans[2] * 2, chans[1])
        self.deconv8_4 = Conv2x_IN(chans[1] * 2, chans[0])
        self.conv4 = nn.Conv2d(chans[0] * 2 + vit_feat_dim, chans[0] * 2 + vit_feat_dim, 3, padding=1)
        self.d_out = [chans[0] * 2 + vit_feat_dim, chans[1] * 2, chans[2] * 2, chans[3]]

    def forward(self, x):
        H, W = x.shape[-2:]
        h, w = get_resize_keep_aspect_ratio(H, W, divider=112, max_H=1344, max_W=1344)
        with torch.no_grad():
            vit = self.dino(F.interpolate(x, size=(h, w), mode='bilinear', align_corners=False))['out']
        vit_feat = F.interpolate(vit, size=(H // 4, W // 4), mode='bilinear', align_corners=True)
        x4 = self.stages[0](self.stem(x))
        x8 = self.stages[1](x4)
        x16 = self.stages[2](x8)
        x32 = self.stages[3](x16)
        x16 = self.deconv32_16(x32, x16)
        x8 = self.deconv16_8(x16, x8)
        x4 = self.conv4(torch.cat([self.deconv8_4(x8, x4), vit_feat], 1))
        return [x4, x8, x16, x32], vit_feat


class ContextNetDino(nn.Module):
    def __init__(self, args, output_dim=((128, 128, 128), (128, 128, 128)), norm_fn='batch', downsample=2):
        super().__init__()
        vit_dim = DepthAnythingFeature.model_configs[args.vit_size]['features'] // 2
        self.conv1 = nn.Conv2d(3, 32, 4, 4)
        self.norm1 = nn.BatchNorm2d(32)
        self.conv2 = nn.Conv2d(32 + vit_dim, 32, 3, padding=1)
        self.layer4 = nn.Conv2d(32, 32, 3, 2, 1)
        self.layer5 = nn.Conv2d(32, 32, 3, 2, 1)
        self.outputs04 = nn.ModuleList(nn.Conv2d(32, dim[2], 3, padding=1) for dim in output_dim)
        self.outputs08 = nn.ModuleList(nn.Conv2d(32, dim[1], 3, padding=1) for dim in output_dim)
        self.outputs16 = nn.ModuleList(nn.Conv2d(32, dim[0], 3, padding=1) for dim in output_dim)

    def forward(self, x_in, vit_feat, dual_inp=False, num_layers=3):
        x = torch.relu(self.conv2(torch.cat([torch.relu(self.norm1(self.conv1(x_in))), vit_feat], 1)))
        outputs04 = [f(x) for f in self.outputs04]
        y = torch.relu(self.layer4(x))
        outputs08 = [f(y) for f in self.outputs08]
        z = torch.relu(self.layer5(y))
        outputs16 = [f(z) for f in self.outputs16]
        return (outputs04, outputs08, outputs16)
