"""The FoundationStereo / Fast-FoundationStereo adapters on the stand-ins in tests/support/standin_foundation_stereo (the
real repositories' layout, imports, torch.hub and timm calls and return values; tiny layers and an exact block
matcher for disparity): features and disparity against the stand-ins' own modules, pruned widths, both encoders in
one process in either order, offline construction, and every failure as one line."""

from __future__ import annotations

import math
import socket
import sys
import types
import urllib.request

import pytest
import torch
import torch.nn.functional as F

from sgmodel.config import DecoderParams, ModelParams, PredictorParams
from sgmodel.encoders import create_encoder
from sgmodel.model.network import create_model
from sgmodel.weights import WeightsError
from tests.support.foundation_standins import (FFS_CFG, FFS_REPO, FS_CFG, FS_REPO, PRUNED_WIDTHS, SHIFT, copy_checkout,
                                               save_ffs_model, save_fs_checkpoint, shifted_pair)

CHECKOUT_NAMES = ("core", "Utils", "depth_anything", "dinov2", "foundation_stereo_ori")


@pytest.fixture(scope="module")
def fs_checkpoint(tmp_path_factory):
    return save_fs_checkpoint(tmp_path_factory.mktemp("fs") / "23-51-11")


@pytest.fixture(scope="module")
def ffs_model_file(tmp_path_factory):
    return save_ffs_model(tmp_path_factory.mktemp("ffs") / "23-36-37" / "model_best_bp2_serialize.pth")


def fs(path, repo=FS_REPO):
    return create_encoder("foundation-stereo", weights=str(path), repo=str(repo))


def ffs(path, repo=FFS_REPO):
    return create_encoder("fast-foundation-stereo", weights=str(path), repo=str(repo))


def normalised(x: torch.Tensor) -> torch.Tensor:
    """[0,1] -> the stand-ins' input: [0,255], padded at the bottom and right to multiples of 32 (edge
    replication), ImageNet-normalised."""
    from tests.support.standin_foundation_stereo.standin_stereo import normalise

    h, w = x.shape[-2:]
    return normalise(F.pad(x * 255, (0, -w % 32, 0, -h % 32), mode="replicate"))


def check_frozen(enc) -> None:
    enc.train()
    assert not any(m.training for m in enc.modules())
    assert all(not p.requires_grad for p in enc.parameters())


def test_foundation_stereo_features_and_disparity(fs_checkpoint):
    enc = fs(fs_checkpoint)
    check_frozen(enc)
    assert enc.feature_scales == (4, 8, 16, 32)
    assert enc.feature_channels == (128 + 16, 192 + 16, 320 + 16, 304)  # image + context + recurrent per scale
    assert len(enc.weights_sha256) == 64
    saved = torch.load(fs_checkpoint, weights_only=True)["model"]
    assert all(torch.equal(v, saved[k]) for k, v in enc.model.state_dict().items())  # the probe ran in eval mode
    left, right = shifted_pair()
    out = enc(left, right)
    assert out.disparity.shape == (1, 1, 70, 90)
    assert torch.all(out.disparity[..., 4:-4, SHIFT + 4:-4] == SHIFT)  # [0,1] scaled, padded, cropped right
    for f, c, s in zip(out.features, enc.feature_channels, enc.feature_scales):
        assert f.shape == (1, c, math.ceil(70 / s), math.ceil(90 / s)) and not f.requires_grad
    # The reference: the stand-in's modules called directly, as its forward calls them, on the padded pair.
    m, L, R = enc.model, normalised(left), normalised(right)
    with torch.no_grad():
        image, vit = m.feature(torch.cat([L, R]))
        cnet = m.cnet(L, vit_feat=vit[:1], num_layers=3)
        net, inp = [torch.tanh(x[0]) for x in cnet], [torch.relu(x[1]) for x in cnet]
        from tests.support.standin_foundation_stereo.standin_stereo import block_match

        disp, geo = F.avg_pool2d(block_match(L, R), 4) / 4, m.proj_cmb(image[0][:1])
        for _ in range(32):
            net, _, delta = m.update_block(net, inp, geo, disp, None)
            disp = disp + delta
    for i, s in enumerate((4, 8, 16, 32)):
        h, w = math.ceil(70 / s), math.ceil(90 / s)
        expected = [image[i][:1]] + ([inp[i], net[i]] if i < 3 else [])
        assert torch.allclose(out.features[i], torch.cat(expected, 1)[..., :h, :w], atol=1e-6), s


def test_fast_foundation_stereo_features_and_demo_settings(ffs_model_file):
    enc = ffs(ffs_model_file)
    check_frozen(enc)
    assert enc.feature_channels == (224, 192, 320, 304) and enc.feature_scales == (4, 8, 16, 32)
    assert enc.model.args.valid_iters == 8 and enc.model.args.max_disp == 192  # their demo's, over the pickled 22/416
    left, right = shifted_pair(64, 96)
    out = enc(left, right)
    assert torch.all(out.disparity[..., 4:-4, SHIFT + 4:-4] == SHIFT)
    with torch.no_grad():
        direct = enc.model.feature(torch.cat([normalised(left), normalised(right)]))
    for f, d, s in zip(out.features, direct, (4, 8, 16, 32)):
        assert torch.equal(f, d[:1, :, : math.ceil(64 / s), : 96 // s])


def test_pruned_widths_come_from_the_loaded_model(tmp_path):
    path = save_ffs_model(tmp_path / "20-30-48" / "model_best_bp2_serialize.pth", pruned=True)
    enc = ffs(path)
    assert enc.feature_channels == PRUNED_WIDTHS != tuple(enc.model.feature.d_out)
    assert enc.model.update_block.encoder.convc1.out_channels == 56
    params = ModelParams(resolution=32, padding=2, decoder=DecoderParams(channels=16, groups=4),
                         predictor=PredictorParams(channels=16, groups=4))
    model = create_model(params, encoder=enc)  # the decoder is sized from the measured widths
    left, right = shifted_pair(32, 32)
    pred = model(left, right, torch.tensor([[[40.0, 0, 16], [0, 40, 16], [0, 0, 1]]]), torch.tensor([0.1]))
    assert torch.isfinite(pred.gaussians["means"]).all()


def checkout_modules() -> list[str]:
    return [n for n in sys.modules if n.split(".")[0] in CHECKOUT_NAMES]


@pytest.mark.parametrize("fast_first", [True, False])
def test_both_encoders_in_one_process_in_either_order(fs_checkpoint, ffs_model_file, fast_first):
    path_before = list(sys.path)
    build = [lambda: ffs(ffs_model_file), lambda: fs(fs_checkpoint)]
    first, second = (build if fast_first else build[::-1])
    a = first()
    assert checkout_modules() == [] and sys.path == path_before
    b = second()
    assert checkout_modules() == [] and sys.path == path_before
    left, right = shifted_pair(64, 64)
    for enc in (a, b, first()):  # the one built first still runs, and building it again reuses its modules
        assert torch.all(enc(left, right).disparity[..., 4:-4, SHIFT + 4:-4] == SHIFT)
    assert type(first().model) is type(a.model)


def test_other_core_and_utils_in_the_environment_do_not_interfere(fs_checkpoint, ffs_model_file, monkeypatch):
    """Fast-FoundationStereo's regular ``core`` package on sys.path (it wins over FoundationStereo's namespace
    package in a plain import) and a foreign ``Utils`` module already imported."""
    foreign = types.ModuleType("Utils")
    monkeypatch.setitem(sys.modules, "Utils", foreign)
    monkeypatch.syspath_prepend(str(FFS_REPO))
    assert fs(fs_checkpoint).feature_channels[0] == 144 and ffs(ffs_model_file).feature_channels[0] == 224
    assert sys.modules["Utils"] is foreign and str(FFS_REPO) in sys.path and "core" not in sys.modules


def test_offline_with_an_empty_torch_hub_cache(tmp_path, monkeypatch):
    """A fresh checkout (its modules imported for the first time), TORCH_HOME empty, every way out refused."""
    hub = tmp_path / "torch_home"
    hub.mkdir()
    monkeypatch.setenv("TORCH_HOME", str(hub))
    repo = copy_checkout(FS_REPO, tmp_path / "FoundationStereo")
    weights = save_fs_checkpoint(tmp_path / "23-51-11", repo)
    attempts = []

    def refuse(*args, **kwargs):
        attempts.append(args[:1])
        raise AssertionError(f"network access attempted: {args[:1]}")

    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(urllib.request, "urlopen", refuse)
    enc = fs(weights, repo)
    assert attempts == [] and list(hub.iterdir()) == []
    assert enc.model.feature.dino.depth_anything.pretrained.patch_size == 14  # DINOv2 from the vendored dinov2/


def test_timm_backbones_are_built_without_pretrained_weights(tmp_path, monkeypatch):
    """With timm installed, both repositories call timm.create_model('edgenext_small', pretrained=True)."""
    from tests.support.standin_foundation_stereo.standin_stereo import TinyEdgeNext

    calls = []

    def create_model(name, pretrained=False, **kwargs):
        calls.append((name, pretrained))
        if pretrained:  # what timm would do: fetch the weights from a model hub
            socket.create_connection(("hub.invalid", 443))
        return TinyEdgeNext()

    monkeypatch.setitem(sys.modules, "timm", types.SimpleNamespace(create_model=create_model))
    repo = copy_checkout(FS_REPO, tmp_path / "FoundationStereo")
    fs(save_fs_checkpoint(tmp_path / "fs", repo), repo)
    repo = copy_checkout(FFS_REPO, tmp_path / "Fast-FoundationStereo")
    ffs(save_ffs_model(tmp_path / "ffs" / "model.pth", repo), repo)
    assert calls and all(c == ("edgenext_small", False) for c in calls)


def one_line_error(match: str, build) -> str:
    with pytest.raises(WeightsError, match=match) as info:
        build()
    assert "\n" not in str(info.value), str(info.value)
    return str(info.value)


def test_network_reached_for_while_building_is_one_line(tmp_path, fs_checkpoint):
    repo = copy_checkout(FS_REPO, tmp_path / "FoundationStereo")
    dpt = repo / "depth_anything" / "dpt.py"
    dpt.write_text(dpt.read_text().replace("pretrained=False", "pretrained=True"))  # DINOv2 would download
    one_line_error(r"reached for the network \(weights.invalid:443\)", lambda: fs(fs_checkpoint, repo))


def test_missing_vendored_hub_repository(tmp_path, fs_checkpoint):
    repo = copy_checkout(FS_REPO, tmp_path / "FoundationStereo")
    (repo / "dinov2" / "hubconf.py").unlink()
    one_line_error("loads facebookresearch/dinov2 through torch.hub, and the checkout has no dinov2/hubconf.py",
                   lambda: fs(fs_checkpoint, repo))


def test_import_failures_say_what_is_missing(tmp_path, fs_checkpoint, monkeypatch):
    repo = copy_checkout(FS_REPO, tmp_path / "a" / "FoundationStereo")
    module = repo / "core" / "foundation_stereo.py"
    module.write_text("import skimage_not_installed_xyz\n" + module.read_text())
    one_line_error("needs the Python package 'skimage_not_installed_xyz', which is not installed here",
                   lambda: fs(fs_checkpoint, repo))
    repo = copy_checkout(FS_REPO, tmp_path / "b" / "FoundationStereo")
    (repo / "Utils.py").write_text("AMP_DTYPE = None\n")  # another repository's Utils.py: not a missing package
    text = one_line_error(r"importing core.foundation_stereo failed \(ImportError: cannot import name "
                          r"'freeze_model' from 'Utils'", lambda: fs(fs_checkpoint, repo))
    assert "install" not in text
    broken = tmp_path / "site" / "broken_pkg_xyz"  # installed, but its native library is missing (open3d, libusb)
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text("raise ImportError('libusb-1.0.so.0: cannot open shared object file')\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    repo = copy_checkout(FS_REPO, tmp_path / "c" / "FoundationStereo")
    (repo / "Utils.py").write_text("import broken_pkg_xyz\n" + (repo / "Utils.py").read_text())
    one_line_error(r"imports 'broken_pkg_xyz', which fails to load here \(ImportError: libusb-1.0.so.0",
                   lambda: fs(fs_checkpoint, repo))


def test_every_failure_is_one_line(tmp_path, fs_checkpoint, ffs_model_file):
    for name in ("foundation-stereo", "fast-foundation-stereo"):
        one_line_error("--encoder-repo PATH", lambda: create_encoder(name, weights=str(fs_checkpoint)))
        one_line_error("no core/foundation_stereo.py", lambda: create_encoder(name, weights="x", repo=str(tmp_path)))
    one_line_error("needs its checkpoint: pass --encoder-weights PATH", lambda: create_encoder(
        "foundation-stereo", repo=str(FS_REPO)))
    one_line_error("no such file", lambda: fs(tmp_path / "absent.pth"))
    lonely = tmp_path / "elsewhere" / "model_best_bp2.pth"
    lonely.parent.mkdir()
    lonely.write_bytes(fs_checkpoint.read_bytes())
    one_line_error("no cfg.yaml beside the checkpoint", lambda: fs(lonely))
    (lonely.parent / "cfg.yaml").write_text("hidden_dims: [8, 8\n")
    one_line_error("not a readable cfg.yaml", lambda: fs(lonely))
    (lonely.parent / "cfg.yaml").write_text("[1, 2]\n")
    one_line_error("cfg.yaml holds a list, expected a mapping", lambda: fs(lonely))
    (lonely.parent / "cfg.yaml").write_text("n_gru_layers: 3\n")
    one_line_error(r"building FoundationStereo with .*cfg.yaml failed \(\w*AttributeError: .*hidden_dims",
                   lambda: fs(lonely))
    (lonely.parent / "cfg.yaml").write_text(str({**FS_CFG, "hidden_dims": [4, 4, 4]}))
    one_line_error("not a FoundationStereo checkpoint for", lambda: fs(lonely))
    one_line_error("expected the serialised FastFoundationStereo", lambda: ffs(fs_checkpoint))
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a pickle")
    one_line_error("not a serialised Fast-FoundationStereo model", lambda: ffs(garbage))
    broken = save_ffs_model(tmp_path / "broken.pth", cfg={k: v for k, v in FFS_CFG.items() if k != "mixed_precision"})
    one_line_error(r"the loaded fast-foundation-stereo model fails on a 32x32 test pair \(AttributeError: "
                   r"mixed_precision\)", lambda: ffs(broken))
