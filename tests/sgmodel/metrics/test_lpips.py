"""LPIPS-VGG (sgmodel.metrics.lpips) and the objective (sgmodel.train.losses) against a float64 reference written here.

The real LPIPS v0.1 linear layers (fetched from the ``lpips`` wheel) with random VGG16 weights saved in
torchvision's key layout: the ImageNet VGG16 file cannot be downloaded here. The reference rebuilds the
VGG16 trunk from the state dict's keys (conv + ReLU per key, a 2x2 max-pool before each new stage) and
the LPIPS arithmetic from the paper: scale, normalise over channels, squared difference, weighted channel
sum, spatial mean, sum over layers.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from sgmodel import weights
from sgmodel.metrics.image import lpips
from sgmodel.metrics.lpips import LPIPS, create_lpips, find_vgg16_weights, tap_distance
from sgmodel.train.losses import create_objective
from sgmodel.weights import WeightsError
from tests.support.model_helpers import record_compile

#: torchvision's VGG16 `features` indices of the 13 convolutions, and of the first conv of stages 2-5.
CONV_INDICES = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
STAGE_STARTS = (5, 10, 17, 24)
CHANNELS = (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)


@pytest.fixture(scope="module")
def lin_path():
    path = weights.cached_path("lpips-vgg")
    if not path.is_file():
        try:
            path = weights.fetch("lpips-vgg")
        except WeightsError as e:
            pytest.skip(f"LPIPS v0.1 linear layers not cached and `sgmodel weights fetch lpips-vgg` failed: {e}")
    return path


def random_vgg_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """Random VGG16 weights with torchvision's keys, including the classifier head of the real file."""
    g = torch.Generator().manual_seed(seed)
    state, c_in = {}, 3
    for idx, c in zip(CONV_INDICES, CHANNELS):
        std = (2.0 / (9 * c_in)) ** 0.5
        state[f"features.{idx}.weight"] = torch.randn(c, c_in, 3, 3, generator=g) * std
        state[f"features.{idx}.bias"] = torch.randn(c, generator=g) * 0.05
        c_in = c
    state["classifier.0.weight"] = torch.zeros(8, 8)  # shape irrelevant: the head is dropped on load
    state["classifier.0.bias"] = torch.zeros(8)
    return state


@pytest.fixture(scope="module")
def vgg_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("vgg") / "vgg16-random.pth"
    torch.save(random_vgg_state(), path)
    return path


@pytest.fixture(scope="module")
def net(vgg_path, lin_path) -> LPIPS:
    return create_lpips(vgg_path, lin_path)


def reference_layers(x: torch.Tensor, state: dict) -> list[torch.Tensor]:
    """Float64 VGG16 relu1_2 .. relu5_3 from the state dict alone."""
    feats = []
    x = x.double()
    for k, idx in enumerate(CONV_INDICES):
        if idx in STAGE_STARTS:
            feats.append(x)
            x = F.max_pool2d(x, 2, 2)
        x = F.relu(F.conv2d(x, state[f"features.{idx}.weight"].double(), state[f"features.{idx}.bias"].double(),
                            padding=1))
    feats.append(x)
    return feats


def reference_lpips(a: np.ndarray, b: np.ndarray, state: dict, lins: list[np.ndarray], spatial: bool):
    """LPIPS v0.1 in float64; a, b [N, 3, H, W] in [0, 1]. spatial: per-pixel map [N, 1, H, W]."""
    shift = np.array([-0.030, -0.088, -0.188])[None, :, None, None]
    scale = np.array([0.458, 0.448, 0.450])[None, :, None, None]
    fa = reference_layers(torch.from_numpy((2 * a - 1 - shift) / scale), state)
    fb = reference_layers(torch.from_numpy((2 * b - 1 - shift) / scale), state)
    total = 0.0
    for f0, f1, w in zip(fa, fb, lins):
        f0, f1 = f0.numpy(), f1.numpy()
        n0 = f0 / (np.sqrt((f0 ** 2).sum(axis=1, keepdims=True)) + 1e-10)
        n1 = f1 / (np.sqrt((f1 ** 2).sum(axis=1, keepdims=True)) + 1e-10)
        d = ((n0 - n1) ** 2 * w.reshape(1, -1, 1, 1)).sum(axis=1, keepdims=True)
        total = total + (bilinear(d, a.shape[-2:]) if spatial else d.mean(axis=(1, 2, 3)))
    return total


def bilinear(m: np.ndarray, size) -> np.ndarray:
    """Bilinear resize of [N, 1, h, w] to size with half-pixel centres (source clamped at 0 and the edge)."""
    def axis(n_in, n_out):
        src = np.maximum((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0)
        i0 = np.minimum(np.floor(src).astype(int), n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        return i0, i1, src - i0
    y0, y1, ty = axis(m.shape[2], size[0])
    x0, x1, tx = axis(m.shape[3], size[1])
    rows = m[:, :, y0] * (1 - ty)[:, None] + m[:, :, y1] * ty[:, None]
    return rows[..., x0] * (1 - tx) + rows[..., x1] * tx


def test_matches_float64_reference(net, vgg_path, lin_path):
    rng = np.random.default_rng(1)
    a = rng.random((2, 3, 34, 26))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    state = torch.load(vgg_path, weights_only=True)
    lins = [v.numpy().astype(np.float64) for v in torch.load(lin_path, map_location="cpu", weights_only=True).values()]
    want = reference_lpips(a, b, state, lins, spatial=False)
    got = net(torch.from_numpy(a).float(), torch.from_numpy(b).float()).double().numpy()
    np.testing.assert_allclose(got, want, rtol=1e-4)
    want_map = reference_lpips(a, b, state, lins, spatial=True)
    got_map = net.per_pixel(torch.from_numpy(a).float(), torch.from_numpy(b).float()).double().numpy()
    assert got_map.shape == (2, 1, 34, 26)
    np.testing.assert_allclose(got_map, want_map, rtol=1e-4, atol=1e-7)
    # inputs already in [-1, 1]
    got_pm = net(torch.from_numpy(2 * a - 1).float(), torch.from_numpy(2 * b - 1).float(), zero_one=False)
    np.testing.assert_allclose(got_pm.double().numpy(), want, rtol=1e-4)


def test_zero_for_identical_positive_otherwise_batched(net):
    g = torch.Generator().manual_seed(2)
    a = torch.rand(2, 2, 3, 24, 24, generator=g)
    b = (a + 0.1 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    same = net(a, a)
    assert same.shape == (2, 2) and torch.all(same == 0)
    diff = net(a, b)
    assert diff.shape == (2, 2) and torch.all(diff > 0)
    torch.testing.assert_close(diff[1, 1], net(a[1, 1], b[1, 1]))  # batching does not mix images
    assert torch.all(net.per_pixel(a, a) == 0)


def test_masked_lpips_of_a_target_without_a_valid_pixel_is_nan_and_the_others_unchanged(net):
    g = torch.Generator().manual_seed(4)
    a = torch.rand(3, 3, 24, 24, generator=g)
    b = (a + 0.1 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    mask = torch.rand(3, 1, 24, 24, generator=g) < 0.5
    mask[1] = False
    got = lpips(net, a, b, mask)
    assert torch.isnan(got[1]) and torch.isfinite(got[[0, 2]]).all()
    torch.testing.assert_close(got[2], lpips(net, a[2:], b[2:], mask[2:])[0])  # no other target is touched


def test_gradient_reaches_input_not_weights(net):
    net.train()
    assert not net.training and not net.vgg.training
    assert all(not p.requires_grad for p in net.parameters())
    a = torch.rand(1, 3, 32, 32, requires_grad=True)
    b = torch.rand(1, 3, 32, 32)
    net(a, b).sum().backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    assert all(p.grad is None for p in net.parameters())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (the bf16 channels-last loss path)")
def test_bf16_training_path_stays_close_to_float32_on_cuda(net):
    """Under CUDA autocast the loss runs VGG16 channels-last in bf16: close to the float32 path in value,
    and its input gradient points the same way."""
    cuda = net.to("cuda")
    g = torch.Generator(device="cuda").manual_seed(3)
    a = torch.rand(4, 3, 64, 64, device="cuda", generator=g)
    b = (a + 0.05 * torch.randn(a.shape, device="cuda", generator=g)).clamp(0, 1).requires_grad_(True)
    want = cuda(a, b)
    (g32,) = torch.autograd.grad(want.sum(), b)
    with torch.autocast("cuda", dtype=torch.bfloat16):
        got = cuda(a, b).float()
    (g16,) = torch.autograd.grad(got.sum(), b)
    torch.testing.assert_close(got, want, rtol=2e-2, atol=1e-4)
    assert F.cosine_similarity(g16.flatten(), g32.flatten(), dim=0) > 0.98
    net.to("cpu")


def _tap_distance_by_autograd(a, b, w):
    """The tap distance as plain operations (autograd differentiates it)."""
    ua = a / (torch.linalg.vector_norm(a, dim=1, keepdim=True) + 1e-10)
    ub = b / (torch.linalg.vector_norm(b, dim=1, keepdim=True) + 1e-10)
    return ((ua - ub) ** 2 * w).sum(dim=1, keepdim=True)


def test_tap_distance_backward_matches_autograd_in_float64():
    g = torch.Generator().manual_seed(4)
    a = torch.rand(2, 5, 3, 4, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(2, 5, 3, 4, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.rand(1, 5, 1, 1, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x, y: tap_distance(x, y, w), (a, b))
    with torch.no_grad():  # degenerate pixels: all-zero features on one side or both (ReLU outputs)
        a[0, :, 0, 0] = 0
        b[1, :, 2, 3] = 0
        a[1, :, 1, 1] = b[1, :, 1, 1] = 0
    up = torch.rand(2, 1, 3, 4, generator=g, dtype=torch.float64)
    ours = tap_distance(a, b, w)
    ref = _tap_distance_by_autograd(a, b, w)
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=0)
    got, want = torch.autograd.grad(ours, (a, b), up), torch.autograd.grad(ref, (a, b), up)
    for x, y in zip(got, want):
        assert torch.isfinite(x).all()
        torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-10 * y.abs().max().item())
    (only_b,) = torch.autograd.grad(tap_distance(a.detach(), b, w), b, up)  # the training case: targets frozen
    torch.testing.assert_close(only_b, want[1], rtol=1e-10, atol=1e-10 * want[1].abs().max().item())
    half = tap_distance(a.detach().bfloat16(), b.detach().bfloat16(), w.float())
    assert half.dtype == torch.float32 and torch.isfinite(half).all()


def test_strict_loading_names_bad_keys(tmp_path, lin_path):
    state = random_vgg_state()
    state["features.29.weight"] = state.pop("features.28.weight")
    bad = tmp_path / "renamed.pth"
    torch.save(state, bad)
    with pytest.raises(WeightsError, match="features.2[89].weight"):
        create_lpips(bad, lin_path)
    state = random_vgg_state()
    del state["features.0.bias"]
    torch.save(state, bad)
    with pytest.raises(WeightsError, match="features.0.bias"):
        create_lpips(bad, lin_path)
    lin = torch.load(lin_path, map_location="cpu", weights_only=True)
    lin["lin5.model.1.weight"] = lin["lin4.model.1.weight"]
    torch.save(lin, tmp_path / "lin.pth")
    with pytest.raises(WeightsError, match="lin5"):
        create_lpips(tmp_path / "renamed.pth", tmp_path / "lin.pth")


def test_missing_vgg_weights(tmp_path, monkeypatch, lin_path, vgg_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    assert find_vgg16_weights() is None and create_lpips(None, lin_path) is None
    with pytest.raises(WeightsError, match="--lpips-vgg"):
        create_lpips(tmp_path / "nope.pth", lin_path)
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / "vgg16-397923af.pth").write_bytes(vgg_path.read_bytes())  # right name, wrong content
    assert find_vgg16_weights() == hub / "vgg16-397923af.pth"
    with pytest.raises(WeightsError, match="sha256"):
        create_lpips(None, lin_path)


def test_objective_uses_lpips_or_falls_back_to_ssim(tmp_path, monkeypatch, vgg_path, lin_path):
    from skimage.metrics import structural_similarity

    g = torch.Generator().manual_seed(3)
    target = torch.rand(2, 2, 3, 24, 24, generator=g, dtype=torch.float64)
    render = (target + 0.1 * torch.randn(target.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    obj = create_objective(None, lin_path)
    assert obj.name == "mse+ssim" and "no VGG16 weights" in obj.description
    assert obj.to_config()["name"] == "mse+ssim"
    loss, parts = obj(render, target)
    t, r = target.numpy(), render.detach().numpy()
    ssim_ref = np.mean([structural_similarity(t[i, j], r[i, j], gaussian_weights=True, sigma=1.5,
                                              use_sample_covariance=False, data_range=1, channel_axis=0)
                        for i in range(2) for j in range(2)])
    want = np.mean((t - r) ** 2) + 0.05 * (1 - ssim_ref)
    assert abs(loss.item() - want) < 1e-10 and abs(parts["ssim"].item() - ssim_ref) < 1e-10
    loss.backward()
    assert torch.isfinite(render.grad).all()

    obj = create_objective(vgg_path, lin_path)
    assert obj.name == "mse+lpips-vgg" and obj.to_config()["vgg16_sha256"] == weights.sha256_file(vgg_path)
    loss, parts = obj(render.float(), target.float())
    want = parts["mse"] + 0.05 * obj.lpips_net(target.float(), render.float()).mean()
    torch.testing.assert_close(loss, want)


def test_compiled_trunk_is_handed_to_torch_compile_and_computes_the_same(vgg_path, lin_path, monkeypatch):
    """``create_objective(compile_trunk=True)`` gives LPIPS's trunk (scaling layer and VGG16 to relu5_3) to
    ``torch.compile`` with static shapes and runs both image sides through it, with the eager values; the
    loss's config (compared on resume) does not change. Compilation is replaced by a recorder here (on the
    CPU inductor would compile VGG16 for minutes); the real compiled kernels are the CUDA test below."""
    from sgmodel.args import params_from_args
    from sgmodel.cli import build_parser

    seen = record_compile(monkeypatch)
    g = torch.Generator().manual_seed(4)
    target = torch.rand(2, 3, 32, 32, generator=g)
    render = (target + 0.1 * torch.randn(target.shape, generator=g)).clamp(0, 1).requires_grad_(True)
    eager = create_objective(vgg_path, lin_path)
    compiled = create_objective(vgg_path, lin_path, compile_trunk=True)
    assert seen == [{"dynamic": False}]
    want, _ = eager(render, target)
    got, _ = compiled(render, target)
    assert seen[1:] == ["call", "call"]  # the target's side, then the render's
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert compiled.to_config() == eager.to_config()
    # `sgmodel train` compiles by default (on CUDA); --no-compile-lpips turns it off
    argv = ["train", "--data", "d", "--out", "o"]
    assert params_from_args(build_parser().parse_args(argv))[1].compile_lpips
    assert not params_from_args(build_parser().parse_args(argv + ["--no-compile-lpips"]))[1].compile_lpips


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (torch.compile of the training loss's VGG16)")
@pytest.mark.parametrize("amp", [True, False])
def test_compiled_trunk_matches_eager_on_cuda(vgg_path, lin_path, amp):
    """The compiled trunk against the eager one on CUDA, in the bf16 training path and in float32 (cuDNN's
    TF32 off: with it the gradients differ by 8e-3 in relative L2): the LPIPS term and its gradient with
    respect to the render agree to rounding. The compiled graph may run its convolutions in another layout
    and so with other cuDNN algorithms: in float32 the gradients differed by 7.7e-4 on an H100 with these
    weights (1.5e-7 with PyTorch's default VGG16 initialisation), the values by less than 1e-5."""
    g = torch.Generator(device="cuda").manual_seed(5)
    target = torch.rand(8, 3, 64, 64, device="cuda", generator=g)
    render = (target + 0.05 * torch.randn(target.shape, device="cuda", generator=g)).clamp(0, 1).requires_grad_(True)
    results = []
    for compile_trunk in (False, True):
        obj = create_objective(vgg_path, lin_path, device="cuda", amp=amp, compile_trunk=compile_trunk)
        with torch.backends.cudnn.flags(enabled=True, allow_tf32=amp):
            loss, parts = obj(render, target)
            (grad,) = torch.autograd.grad(loss, render)
        results.append((parts["lpips"], grad))
    (want, g_want), (got, g_got) = results
    if amp:
        torch.testing.assert_close(got, want, rtol=1e-2, atol=1e-4)
        assert F.cosine_similarity(g_got.flatten(), g_want.flatten(), dim=0) > 0.99
    else:
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)
        assert ((g_got - g_want).norm() / g_want.norm()).item() < 2e-3


def test_training_compiles_the_trunk_only_on_cuda_with_triton(monkeypatch):
    from sgmodel.model import layers

    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    monkeypatch.setattr(layers, "triton_installed", lambda: True)
    assert layers.compiles(cuda) and not layers.compiles(cuda, wanted=False)
    assert not layers.compiles(cpu)
    monkeypatch.setattr(layers, "triton_installed", lambda: False)
    assert not layers.compiles(cuda)
