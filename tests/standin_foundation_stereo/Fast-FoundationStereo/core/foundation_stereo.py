"""Stand-in for NVlabs/Fast-FoundationStereo's ``core/foundation_stereo.py`` (see ../../README.md)."""

from __future__ import annotations

import torch
from torch import nn

from standin_foundation_stereo.standin_stereo import Pyramid, block_match, normalise


class Config(dict):
    """Their ``args`` is an OmegaConf DictConfig: attribute access and ``get``."""

    def __getattr__(self, key):
        try:
            return self[key]
        except KeyError as e:
            raise AttributeError(key) from e

    def __setattr__(self, key, value):
        self[key] = value


class FastFoundationStereo(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.args = args
        self.feature = Pyramid()
        self.iters_seen = None

    def forward(self, image1, image2, iters=12, test_mode=False, low_memory=False, init_disp=None, profile=False,
                optimize_build_volume="pytorch1"):
        if optimize_build_volume not in ("pytorch1", "triton"):
            raise RuntimeError(f"Invalid optimize_build_volume: {optimize_build_volume}")
        image1, image2 = normalise(image1), normalise(image2)
        self.feature(torch.cat([image1, image2], 0))
        self.iters_seen = iters
        full = block_match(image1, image2)
        return full if test_mode else (full, [full])
