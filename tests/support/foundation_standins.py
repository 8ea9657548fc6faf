"""Random-weight models of the FoundationStereo stand-ins (tests/support/standin_foundation_stereo) in their releases' file
layout: ``model_best_bp2.pth`` with ``cfg.yaml`` beside it (FoundationStereo), a serialised model file
(Fast-FoundationStereo), and a pruned Fast-FoundationStereo whose layer widths differ from its code's constants."""

from __future__ import annotations

import shutil
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from scripts.checks.foundation_releases import save_ffs_release, save_fs_release

STANDIN = Path(__file__).parent / "standin_foundation_stereo"
FS_REPO, FFS_REPO = STANDIN / "FoundationStereo", STANDIN / "Fast-FoundationStereo"
FS_CFG = {"hidden_dims": [8, 8, 8], "n_gru_layers": 3, "n_downsample": 2, "max_disp": 192, "vit_size": "vits",
          "mixed_precision": False}
FFS_CFG = {"hidden_dims": [8], "n_gru_layers": 1, "max_disp": 416, "vit_size": "vitl", "corr_levels": 2,
           "corr_radius": 1, "mixed_precision": False, "valid_iters": 22}
#: Widths of the pruned variant's feature maps at 1/4, 1/8, 1/16, 1/32 (the code's constants say 224, 192, 320, 304).
PRUNED_WIDTHS = (40, 72, 200, 120)
SHIFT = 5  # px: right(x - SHIFT) = left(x), i.e. true disparity SHIFT


def shifted_pair(h: int = 70, w: int = 90) -> tuple[torch.Tensor, torch.Tensor]:
    """[1,3,h,w] in [0,1]: random texture (smoothed) and the same texture shifted by SHIFT pixels."""
    g = torch.Generator().manual_seed(0)
    tex = F.avg_pool2d(torch.rand(1, 3, h, w + SHIFT, generator=g), 3, 1, 1)
    return tex[..., :w].contiguous(), tex[..., SHIFT:].contiguous()


def copy_checkout(repo: Path, dest: Path) -> Path:
    """A copy of a stand-in checkout (a new folder: its modules are imported afresh)."""
    shutil.copytree(repo, dest, ignore=shutil.ignore_patterns("__pycache__"))
    return dest


def save_fs_checkpoint(folder: Path, repo: Path = FS_REPO, cfg: dict | None = None) -> Path:
    """``folder/model_best_bp2.pth`` (``{"model": state_dict, "global_step", "epoch"}``) and ``folder/cfg.yaml``."""
    return save_fs_release(repo, folder, FS_CFG if cfg is None else cfg)


def save_ffs_model(path: Path, repo: Path = FFS_REPO, cfg: dict | None = None, pruned: bool = False) -> Path:
    """The whole FastFoundationStereo pickled to ``path`` (their release's format), ``pruned`` as in ``prune``."""
    saved = save_ffs_release(repo, path.parent, FFS_CFG if cfg is None else cfg, edit=prune if pruned else None)
    return saved.rename(path)


def prune(model: nn.Module) -> None:
    """Narrow the model's layers after construction, as structured pruning does: the feature maps get
    PRUNED_WIDTHS (extra ``conv8``/``conv16``/``conv32`` layers, as their pruned releases carry) and
    ``update_block.encoder.convc1`` 56 output channels; ``feature.d_out`` keeps the code's constants."""
    f = model.feature
    w4, w8, w16, w32 = PRUNED_WIDTHS
    f.conv4 = nn.Conv2d(f.conv4.in_channels, w4, 1)
    f.conv8, f.conv16, f.conv32 = nn.Conv2d(192, w8, 1), nn.Conv2d(320, w16, 1), nn.Conv2d(304, w32, 1)
    model.proj_cmb = nn.Conv2d(w4, model.proj_cmb.out_channels, 1)
    model.cnet.conv04 = nn.ModuleList(nn.Conv2d(w4, c.out_channels, 3, padding=1) for c in model.cnet.conv04)
    enc = model.update_block.encoder
    enc.convc1 = nn.Conv2d(enc.convc1.in_channels, 56, 1)
    enc.conv = nn.Conv2d(56 + enc.convd1.out_channels, enc.conv.out_channels, 3, padding=1)
