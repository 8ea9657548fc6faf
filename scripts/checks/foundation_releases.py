"""Random-weight models of NVlabs/FoundationStereo and NVlabs/Fast-FoundationStereo in their releases' file layout,
built from the user's checkouts with sgmodel's own pinned, offline import (``sgmodel.encoders.checkout``):

    OUT/FoundationStereo/23-51-11/model_best_bp2.pth + cfg.yaml        (their 23-51-11 release's configuration)
    OUT/Fast-FoundationStereo/23-36-37/model_best_bp2_serialize.pth + cfg.yaml   (the pickled model, code defaults)
    OUT/Fast-FoundationStereo/pruned/model_best_bp2_serialize.pth + cfg.yaml     (narrowed after construction)

The pruned model narrows layers as structured pruning does, leaving the code's constants (``feature.d_out``)
stale: ``update_block.encoder.convc1`` becomes Conv2d(522, 56) (their pruned release's, NVlabs/Fast-FoundationStereo
issue 20), and the feature maps at 1/8, 1/16, 1/32 get PRUNED_FEATURE_WIDTHS through the extra ``conv8``,
``conv16``, ``conv32`` layers their ``Feature.forward`` applies when present (each consumer rebuilt to match).
No weights are downloaded and nothing of theirs is copied: the files are made by their own code.

    python scripts/checks/foundation_releases.py --fs-repo FS --ffs-repo FFS --out OUT

``save_fs_release`` / ``save_ffs_release`` also make the tests' stand-in releases (tests/support/foundation_standins.py).
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from pathlib import Path

import torch
import yaml
from torch import nn

from sgmodel.encoders.foundation import REPO_FLAG, checkout, load_config

#: The model settings of FoundationStereo's 23-51-11 release cfg.yaml.
FS_RELEASE_CFG = {"corr_implementation": "reg", "corr_levels": 2, "corr_radius": 4, "hidden_dims": [128, 128, 128],
                  "low_memory": 0, "max_disp": 416, "mixed_precision": True, "n_downsample": 2, "n_gru_layers": 3,
                  "valid_iters": 32, "vit_size": "vitl"}
#: Fast-FoundationStereo at its code's defaults with the paper's single GRU level (corr_levels 2, radius 4 and
#: volume_dim 28 give convc1's 522 input channels of their release).
FFS_RELEASE_CFG = {"corr_levels": 2, "corr_radius": 4, "cv_group": 8, "volume_dim": 28, "hidden_dims": [128, 128, 128],
                   "low_memory": 0, "max_disp": 416, "mixed_precision": True, "n_gru_layers": 1, "normalize": True,
                   "valid_iters": 8, "vit_size": "vitl"}
PRUNED_CONVC1 = 56
PRUNED_FEATURE_WIDTHS = (128, 256, 240)  # at 1/8, 1/16, 1/32 (their code: 192, 320, 304)


def save_fs_release(repo: Path, folder: Path, cfg: dict = FS_RELEASE_CFG, seed: int = 0) -> Path:
    """``folder/model_best_bp2.pth`` (``{"model", "global_step", "epoch"}``) and ``folder/cfg.yaml``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    code = checkout(repo, "foundation-stereo", "FoundationStereo", "")
    with code.building(REPO_FLAG):
        torch.manual_seed(seed)
        model = code.import_module("core.foundation_stereo", REPO_FLAG).FoundationStereo(
            load_config(folder / "cfg.yaml"))
    path = folder / "model_best_bp2.pth"
    torch.save({"model": model.state_dict(), "global_step": 0, "epoch": 0}, path)
    return path


def save_ffs_release(repo: Path, folder: Path, cfg: dict = FFS_RELEASE_CFG, edit: Callable | None = None,
                     seed: int = 0) -> Path:
    """``folder/model_best_bp2_serialize.pth`` (the whole model pickled; ``edit(model)`` first) and ``cfg.yaml``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    path = folder / "model_best_bp2_serialize.pth"
    code = checkout(repo, "fast-foundation-stereo", "Fast-FoundationStereo", "")
    with code.building(REPO_FLAG):
        module = code.import_module("core.foundation_stereo", REPO_FLAG)
        torch.manual_seed(seed)
        model = module.FastFoundationStereo(load_config(folder / "cfg.yaml"))
        if edit is not None:
            edit(model)
        torch.save(model, path)  # pickling needs the checkout's modules, as loading does
    return path


def prune_ffs(model: nn.Module) -> None:
    """Narrow a real FastFoundationStereo after construction (see the module docstring); call inside the checkout's
    ``building`` block (it uses their ``core.submodule.FeatureAtt``)."""
    feature_att = importlib.import_module("core.submodule").FeatureAtt
    enc = model.update_block.encoder
    enc.convc1 = nn.Conv2d(enc.convc1.in_channels, PRUNED_CONVC1, 1)
    enc.convc2 = nn.Conv2d(PRUNED_CONVC1, PRUNED_CONVC1, 3, padding=1)
    enc.conv = nn.Conv2d(enc.convd2.out_channels + PRUNED_CONVC1, enc.conv.out_channels, 1)
    f, agg, v = model.feature, model.cost_agg, model.volume_dim
    w8, w16, w32 = PRUNED_FEATURE_WIDTHS
    f.conv8, f.conv16, f.conv32 = (nn.Conv2d(c, w, 1) for c, w in zip(f.d_out[1:], PRUNED_FEATURE_WIDTHS))
    agg.feature_att_8, agg.feature_att_up_8 = feature_att(2 * v, w8), feature_att(2 * v, w8)
    agg.feature_att_16, agg.feature_att_up_16 = feature_att(4 * v, w16), feature_att(4 * v, w16)
    agg.feature_att_32 = feature_att(6 * v, w32)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fs-repo", type=Path, required=True, help="checkout of NVlabs/FoundationStereo")
    p.add_argument("--ffs-repo", type=Path, required=True, help="checkout of NVlabs/Fast-FoundationStereo")
    p.add_argument("--out", type=Path, required=True, help="folder for the releases")
    args = p.parse_args()
    print(save_fs_release(args.fs_repo, args.out / "FoundationStereo" / "23-51-11"))
    print(save_ffs_release(args.ffs_repo, args.out / "Fast-FoundationStereo" / "23-36-37"))
    print(save_ffs_release(args.ffs_repo, args.out / "Fast-FoundationStereo" / "pruned", edit=prune_ffs))


if __name__ == "__main__":
    main()
