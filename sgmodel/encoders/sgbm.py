"""``sgbm``: OpenCV semi-global block matching with a weighted-least-squares (WLS) filter, the classical,
CPU-only encoder. It has no learned features (``feature_channels`` = (), ``features`` = []): a model on
it runs its decoder on RGB-D alone.

Per batch element, on the CPU (OpenCV), with the images as 8-bit RGB:

- ``cv2.StereoSGBM`` in the 3-way mode, minDisparity 0, numDisparities = W / 4 rounded up to a multiple
  of 16 (at least 16; 64 at W = 256: disparities up to a quarter of the width, depth down to 4 fx B / W),
  blockSize 5 below W = 640 and 7 above (larger windows for larger images of the same scene), the usual
  smoothness penalties P1 = 8 * 3 * blockSize^2 and P2 = 32 * 3 * blockSize^2, uniquenessRatio 10,
  speckle filtering over windows of (W / 16)^2 / 2 pixels with range 2, disp12MaxDiff 1, preFilterCap 63.
- Both images are padded on the left with numDisparities replicated columns (cropped off afterwards),
  since SGBM leaves that many leftmost columns unmatched; pixels there whose true match lies inside the
  right image are then matched normally.
- A right matcher (``cv2.ximgproc.createRightMatcher``) and ``cv2.ximgproc.createDisparityWLSFilter``
  (lambda 8000, sigma colour 1.5, the left image as guide), which fills holes edge-aware and enforces
  left-right consistency.
- Disparities are OpenCV's fixed point (1/16 px) divided by 16: pixels of the input; every value that
  is not positive and finite is set to 0, which the model reads as "unknown" (z = z_max).

The result is returned as float32 [B,1,H,W] on the input's device.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

from sgmodel.encoders.base import EncoderOutput, StereoEncoder

WLS_LAMBDA = 8000.0
WLS_SIGMA_COLOR = 1.5


def sgbm_parameters(width: int) -> dict[str, int]:
    """StereoSGBM parameters for an image ``width`` pixels wide (see the module docstring)."""
    num_disparities = max(16, 16 * math.ceil(width / 4 / 16))
    block = 5 if width < 640 else 7
    return dict(minDisparity=0, numDisparities=num_disparities, blockSize=block, P1=8 * 3 * block * block,
                P2=32 * 3 * block * block, disp12MaxDiff=1, uniquenessRatio=10,
                speckleWindowSize=max(1, (width // 16) ** 2 // 2), speckleRange=2, preFilterCap=63,
                mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def sgbm_wls_disparity(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Disparity [H,W] float32 in pixels (0 = unknown) of 8-bit RGB images [H,W,3] (left reference)."""
    params = sgbm_parameters(left.shape[1])
    left_matcher = cv2.StereoSGBM_create(**params)
    right_matcher = cv2.ximgproc.createRightMatcher(left_matcher)
    wls = cv2.ximgproc.createDisparityWLSFilter(left_matcher)
    wls.setLambda(WLS_LAMBDA)
    wls.setSigmaColor(WLS_SIGMA_COLOR)
    pad = params["numDisparities"]  # SGBM leaves the first numDisparities columns unmatched: pad them on
    left = cv2.copyMakeBorder(left, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    right = cv2.copyMakeBorder(right, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    d_left = left_matcher.compute(left, right)
    d_right = right_matcher.compute(right, left)
    d = wls.filter(d_left, left, disparity_map_right=d_right)[:, pad:].astype(np.float32) / 16.0
    d[~np.isfinite(d) | (d <= 0)] = 0.0
    return d


class SGBMEncoder(StereoEncoder):
    """Semi-global matching + WLS; disparity only."""

    name = "sgbm"
    feature_channels = ()
    feature_scales = ()
    weights_sha256 = None

    def __init__(self):
        super().__init__()
        self.freeze()

    def max_disparity(self, width: int) -> float:
        """The end of SGBM's search, numDisparities - 1 pixels (``sgbm_parameters``)."""
        return float(sgbm_parameters(width)["numDisparities"] - 1)

    def encode(self, left: Tensor, right: Tensor) -> EncoderOutput:
        def to_u8(x: Tensor) -> np.ndarray:
            img = (x.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8)
            return np.ascontiguousarray(img.permute(1, 2, 0).cpu().numpy())

        out = [torch.from_numpy(sgbm_wls_disparity(to_u8(a), to_u8(b))) for a, b in zip(left, right)]
        return EncoderOutput(disparity=torch.stack(out)[:, None].to(left.device), features=[])
