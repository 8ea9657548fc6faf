"""The FoundationStereo / Fast-FoundationStereo adapters on the stand-ins in tests/standin_foundation_stereo
(same layout, class names, attributes and forward signatures as NVlabs' repositories; tiny layers and an
exact block matcher for disparity)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
import yaml

from sgmodel.encoders import create_encoder
from sgmodel.encoders.foundation import _import_repo
from sgmodel.weights import WeightsError

STANDIN = Path(__file__).parent / "standin_foundation_stereo"
FS_REPO, FFS_REPO = STANDIN / "FoundationStereo", STANDIN / "Fast-FoundationStereo"
CFG = {"hidden_dims": [8, 8, 8], "n_gru_layers": 3, "n_downsample": 2, "max_disp": 192, "mixed_precision": False}
SHIFT = 5  # px: right(x - SHIFT) = left(x), i.e. true disparity SHIFT


def shifted_pair(h: int = 70, w: int = 90) -> tuple[torch.Tensor, torch.Tensor]:
    """[1,3,h,w] in [0,1]: random texture (smoothed) and the same texture shifted by SHIFT pixels."""
    g = torch.Generator().manual_seed(0)
    tex = F.avg_pool2d(torch.rand(1, 3, h, w + SHIFT, generator=g), 3, 1, 1)
    return tex[..., :w].contiguous(), tex[..., SHIFT:].contiguous()


@pytest.fixture
def fs_checkpoint(tmp_path) -> Path:
    """model_best_bp2.pth + cfg.yaml of a stand-in FoundationStereo, as their releases lay them out."""
    module = _import_repo(FS_REPO, "foundation-stereo", "FoundationStereo", "")
    torch.manual_seed(0)
    model = module.FoundationStereo(type("Args", (dict,), {"__getattr__": dict.__getitem__})(CFG))
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(CFG))
    path = tmp_path / "model_best_bp2.pth"
    torch.save({"model": model.state_dict(), "global_step": 0, "epoch": 0}, path)
    return path


@pytest.fixture
def ffs_model_file(tmp_path) -> Path:
    """A serialised stand-in FastFoundationStereo (their release pickles the whole model)."""
    module = _import_repo(FFS_REPO, "fast-foundation-stereo", "Fast-FoundationStereo", "")
    torch.manual_seed(0)
    path = tmp_path / "model_best_bp2_serialize.pth"
    torch.save(module.FastFoundationStereo(module.Config(CFG, valid_iters=22)), path)
    return path


def check_frozen(enc) -> None:
    enc.train()
    assert not any(m.training for m in enc.modules())
    assert all(not p.requires_grad for p in enc.parameters())


def test_foundation_stereo_adapter(fs_checkpoint):
    enc = create_encoder("foundation-stereo", weights=str(fs_checkpoint), repo=str(FS_REPO))
    check_frozen(enc)
    assert enc.feature_scales == (4, 8, 16, 32)
    assert enc.feature_channels == (8 + 16, 12 + 16, 16 + 16, 20)  # image + context + recurrent per scale
    assert len(enc.weights_sha256) == 64
    left, right = shifted_pair()
    out = enc(left, right)
    assert out.disparity.shape == (1, 1, 70, 90)
    interior = out.disparity[..., 4:-4, SHIFT + 4:-4]
    assert torch.all(interior == SHIFT)  # the exact block matcher: inputs scaled, padded, cropped right
    for f, c, s in zip(out.features, enc.feature_channels, enc.feature_scales):
        assert f.shape == (1, c, math.ceil(70 / s), math.ceil(90 / s)) and not f.requires_grad
    # The image features are those of the left view ([0,255] -> ImageNet normalisation, padded to 96x96).
    from standin_foundation_stereo.standin_stereo import normalise

    padded = F.pad(left * 255, (0, 6, 0, 26), mode="replicate")
    direct = enc.model.feature.pyramid(normalise(padded))
    assert torch.allclose(out.features[0][:, :8], direct[0][..., :18, :23])
    assert torch.allclose(out.features[3], direct[3][..., :3, :3])
    # Context = relu of the context half of cnet's output; recurrent = the hidden state after the last update.
    ctx = enc.model.cnet(normalise(padded))
    assert torch.allclose(out.features[1][:, 12:20], torch.relu(ctx[1][1])[..., :9, :12])
    assert enc.model.update_block.calls == 32
    assert not torch.allclose(out.features[0][:, 16:], torch.tanh(ctx[0][0])[..., :18, :23])


def test_fast_foundation_stereo_adapter(ffs_model_file):
    enc = create_encoder("fast-foundation-stereo", weights=str(ffs_model_file), repo=str(FFS_REPO))
    check_frozen(enc)
    assert enc.feature_channels == (8, 12, 16, 20) and enc.feature_scales == (4, 8, 16, 32)
    left, right = shifted_pair(64, 96)
    out = enc(left, right)
    assert enc.model.iters_seen == 8 and enc.model.args.valid_iters == 8
    assert torch.all(out.disparity[..., 4:-4, SHIFT + 4:-4] == SHIFT)
    assert [tuple(f.shape) for f in out.features] == [(1, 8, 16, 24), (1, 12, 8, 12), (1, 16, 4, 6), (1, 20, 2, 3)]


def test_missing_repo_or_weights(tmp_path, fs_checkpoint):
    for name in ("foundation-stereo", "fast-foundation-stereo"):
        with pytest.raises(WeightsError, match="--encoder-repo PATH"):
            create_encoder(name, weights=str(fs_checkpoint))
        with pytest.raises(WeightsError, match="no core/foundation_stereo.py"):
            create_encoder(name, weights=str(fs_checkpoint), repo=str(tmp_path))
    with pytest.raises(WeightsError, match="needs its checkpoint: pass --encoder-weights PATH"):
        create_encoder("foundation-stereo", repo=str(FS_REPO))
    with pytest.raises(WeightsError, match="no such file"):
        create_encoder("foundation-stereo", weights=str(tmp_path / "absent.pth"), repo=str(FS_REPO))
    lonely = tmp_path / "elsewhere" / "model_best_bp2.pth"
    lonely.parent.mkdir()
    lonely.write_bytes(fs_checkpoint.read_bytes())
    with pytest.raises(WeightsError, match="no cfg.yaml beside the checkpoint"):
        create_encoder("foundation-stereo", weights=str(lonely), repo=str(FS_REPO))
    with pytest.raises(WeightsError, match="expected the serialised FastFoundationStereo"):
        create_encoder("fast-foundation-stereo", weights=str(fs_checkpoint), repo=str(FFS_REPO))
