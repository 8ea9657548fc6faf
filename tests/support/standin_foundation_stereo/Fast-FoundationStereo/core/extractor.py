"""Stand-in for Fast-FoundationStereo's ``core/extractor.py``: ``Feature`` returns ``[x4, x8, x16, x32]`` (no
DINOv2; a pruned model may carry extra ``conv8``/``conv16``/``conv32`` layers, applied when present, as in the
real one); ``ContextNetSharedBackbone`` returns ``([hidden, context],)`` at 1/4."""

import torch
from torch import nn

try:
    import timm  # the real module imports it unconditionally; sgmodel's CI has no timm
except ImportError:
    timm = None
from core.submodule import Conv2x_IN

from tests.support.standin_foundation_stereo.standin_stereo import EDGENEXT_SMALL_CHANS, TinyEdgeNext


class ContextNetSharedBackbone(nn.Module):
    def __init__(self, args, c04, c08, c16, output_dim=((128, 128, 128), (128, 128, 128)), norm_fn='batch',
                 downsample=3):
        super().__init__()
        self.args = args
        self.conv04 = nn.ModuleList([nn.Conv2d(c04, output_dim[0][0], 3, padding=1),
                                     nn.Conv2d(c04, output_dim[1][0], 3, padding=1)])

    def forward(self, x4, x8, x16):
        return ([conv(x4) for conv in self.conv04],)


class DepthAnythingFeature:
    model_configs = {'vitl': {'encoder': 'vitl', 'features': 256}, 'vitb': {'encoder': 'vitb', 'features': 128},
                     'vits': {'encoder': 'vits', 'features': 64}}


class Feature(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.args = args
        model = timm.create_model('edgenext_small', pretrained=True, features_only=False) if timm else TinyEdgeNext()
        self.stem, self.stages = model.stem, model.stages
        self.chans = list(EDGENEXT_SMALL_CHANS)
        vit_feat_dim = DepthAnythingFeature.model_configs[self.args.vit_size]['features'] // 2
        self.deconv32_16 = Conv2x_IN(self.chans[3], self.chans[2])
        self.deconv16_8 = Conv2x_IN(self.chans[2] * 2, self.chans[1])
        self.deconv8_4 = Conv2x_IN(self.chans[1] * 2, self.chans[0])
        self.conv4 = nn.Conv2d(self.chans[0] * 2, self.chans[0] * 2 + vit_feat_dim, kernel_size=1)
        self.d_out = [self.chans[0] * 2 + vit_feat_dim, self.chans[1] * 2, self.chans[2] * 2, self.chans[3]]

    def forward(self, x):
        x4 = self.stages[0](self.stem(x))
        x8 = self.stages[1](x4)
        x16 = self.stages[2](x8)
        x32 = self.stages[3](x16)
        x16 = self.deconv32_16(x32, x16)
        x8 = self.deconv16_8(x16, x8)
        x4 = self.conv4(self.deconv8_4(x8, x4))
        if hasattr(self, 'conv8'):
            x8, x16, x32 = self.conv8(x8), self.conv16(x16), self.conv32(x32)
        return [x4, x8, x16, x32]
