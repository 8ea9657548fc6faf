"""sgmodel.model.composer against an independent float64 implementation of the paper's appendix A.

The reference below is written from SPEC section 7 ("Composer") and appendix A with per-pixel Python loops
and its own copies of the paper's constants; it shares no code with sgmodel.model.composer.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sgmodel.model import composer as comp
from tests.support.composer_inputs import make_inputs

C0 = 0.28209479177387814


# ---------------------------------------------------------------------------------------------------------
# Reference (float64, loops)
# ---------------------------------------------------------------------------------------------------------
def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


def _softplus(x: float) -> float:
    return float(np.logaddexp(0.0, x))


def _phi(t: float) -> float:
    return 4.8 * _sigmoid(1.5 * t + math.log(0.2)) + 0.2


def ref_band(z: np.ndarray, K: np.ndarray, baseline: float) -> np.ndarray:
    """z [H,W] -> bool [H,W]: relative forward-difference disparity gradient > 0.05, dilated by 17 x 17."""
    H, W = z.shape
    d = K[0, 0] * baseline / z
    edge = np.zeros((H, W), bool)
    for v in range(H):
        for u in range(W):
            gu = abs(d[v, u + 1] - d[v, u]) if u + 1 < W else 0.0
            gv = abs(d[v + 1, u] - d[v, u]) if v + 1 < H else 0.0
            edge[v, u] = max(gu, gv) / max(d[v, u], 1e-6) > 0.05
    band = np.zeros((H, W), bool)
    for v in range(H):
        for u in range(W):
            band[v, u] = any(edge[vv, uu] for vv in range(max(0, v - 8), min(H, v + 9))
                             for uu in range(max(0, u - 8), min(W, u + 9)))
    return band


def ref_back_depth(z: np.ndarray, dz: np.ndarray) -> np.ndarray:
    H, W = z.shape
    out = np.zeros((H, W))
    for v in range(H):
        for u in range(W):
            window = [z[vv, uu] for vv in range(max(0, v - 4), min(H, v + 5))
                      for uu in range(max(0, u - 4), min(W, u + 5))]
            out[v, u] = max(window) + _softplus(dz[v, u])
    return out


def ref_gaussian(x: np.ndarray, zl: float, u: int, v: int, K: np.ndarray, rgb: np.ndarray, cap: float | None,
                 composer: bool) -> dict:
    """One Gaussian from the 37 branch values x at canvas pixel (u, v) with layer depth zl."""
    fx, fy = K[0, 0], K[1, 1]
    off = [_sigmoid(x[1]) - 0.5, _sigmoid(x[2]) - 0.5]
    mean = zl * np.linalg.inv(K) @ np.array([u + 0.5 + off[0], v + 0.5 + off[1], 1.0])
    s0 = 0.5 * zl / math.sqrt(fx * fy)
    dc = x[10:37].reshape(9, 3)
    if composer:
        c = math.inf if cap is None else 4.0 + math.log(math.exp(cap) - 1.0)
        scale = [min(max(s0 * _phi(min(t, c)), 1e-10), 3.0) for t in x[3:6]]
        q = np.array([1.0, 0.0, 0.0, 0.0]) + 0.1 * x[6:10]
        alpha = _sigmoid(math.log(0.99 / 0.01) + x[0])
        sh = np.zeros((9, 3))
        sh[0] = (rgb - 0.5) / C0 + dc[0]
        for k in range(1, 9):
            degree = 1 if k < 4 else 2
            sh[k] = 0.1 * 0.25**degree * dc[k]
    else:
        scale = [min(max(s0 * math.exp(t), 1e-10), 3.0) if t < 700 else 3.0 for t in x[3:6]]
        q = np.array(x[6:10], dtype=float)
        alpha = _sigmoid(x[0])
        sh = dc.copy()
    n = np.linalg.norm(q)
    q = q / n if n > 1e-12 else np.array([1.0, 0.0, 0.0, 0.0])
    return dict(means=mean, quats=q, scales=np.array(scale), opacities=alpha, sh=sh)


def ref_compose(front, back, dz, z, rgb, K, baseline, back_layer=True, edge_mask="none", composer=True):
    """numpy float64 in, dict of numpy arrays out, layout as sgmodel.model.composer.compose."""
    B, _, H, W = front.shape
    out = {k: [] for k in ("means", "quats", "scales", "opacities", "sh")}
    for b in range(B):
        band = ref_band(z[b, 0], K[b], baseline[b])
        zb = ref_back_depth(z[b, 0], dz[b, 0]) if back_layer else None
        per = {k: [] for k in out}
        layers = [("front", front)] + ([("back", back)] if back_layer else [])
        for name, arr in layers:
            for v in range(H):
                for u in range(W):
                    if name == "front":
                        zl, cap = z[b, 0, v, u], (0.3 if band[v, u] else None)
                    else:
                        zl, cap = zb[v, u], 0.5
                    g = ref_gaussian(arr[b, :, v, u], zl, u, v, K[b], rgb[b, :, v, u], cap, composer)
                    if name == "back" and edge_mask == "hard":
                        g["opacities"] *= float(band[v, u])
                    if name == "back" and edge_mask == "soft":
                        g["opacities"] *= 0.3 + 0.7 * float(band[v, u])
                    for k in per:
                        per[k].append(g[k])
        for k in out:
            out[k].append(np.stack(per[k]))
    return {k: np.stack(v) for k, v in out.items()}


# ---------------------------------------------------------------------------------------------------------
# Fixtures
# ---------------------------------------------------------------------------------------------------------
OPTIONS = [dict(), dict(back_layer=False), dict(edge_mask="hard"), dict(edge_mask="soft"), dict(composer=False),
           dict(composer=False, back_layer=False), dict(composer=False, edge_mask="soft")]


@pytest.fixture(scope="module")
def inputs64():
    return make_inputs()


@pytest.fixture(scope="module")
def references(inputs64):
    arrays = [t.numpy() for t in inputs64]
    return [ref_compose(*arrays, **o) for o in OPTIONS]


# ---------------------------------------------------------------------------------------------------------
# Against the reference
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("i", range(len(OPTIONS)), ids=[str(o) or "default" for o in OPTIONS])
def test_matches_reference_float64(inputs64, references, i):
    out = comp.compose(*inputs64, **OPTIONS[i])
    ref = references[i]
    B, _, H, W = inputs64[0].shape
    N = H * W * (1 if OPTIONS[i].get("back_layer") is False else 2)
    for k, shape in dict(means=(B, N, 3), quats=(B, N, 4), scales=(B, N, 3), opacities=(B, N), sh=(B, N, 9, 3)).items():
        assert tuple(out[k].shape) == shape, k
        assert out[k].dtype == torch.float64, k
        np.testing.assert_allclose(out[k].numpy(), ref[k], rtol=1e-6, atol=1e-6, err_msg=k)


def test_reference_exercises_band_and_caps(inputs64):
    """The fixture is informative: the band covers part of each canvas and some residuals hit the caps."""
    front, back, dz, z, rgb, K, baseline = inputs64
    band = comp.edge_band(z, K, baseline)[:, 0]
    expected = torch.zeros_like(band)
    expected[0, :, 0:11] = True  # edge pixels at column 2 -> columns 0..10
    expected[1, :, 10:] = True  # edge pixels at column 18 -> columns 10..23
    assert torch.equal(band, expected)
    assert (front[:, 3:6] > comp.scale_cap(0.3)).any() and (back[:, 3:6] > comp.scale_cap(0.5)).any()


def test_float32_agrees_with_float64(inputs64):
    out64 = comp.compose(*inputs64)
    out32 = comp.compose(*make_inputs(dtype=torch.float32))
    for k in out64:
        assert out32[k].dtype == torch.float32
        torch.testing.assert_close(out32[k].double(), out64[k], rtol=1e-4, atol=1e-4)


# ---------------------------------------------------------------------------------------------------------
# Zero residuals: the depth-anchored base attributes
# ---------------------------------------------------------------------------------------------------------
def test_zero_residuals_give_base_attributes(inputs64):
    _, _, _, z, rgb, K, baseline = inputs64
    B, _, H, W = z.shape
    zeros = torch.zeros(B, 37, H, W, dtype=torch.float64)
    out = comp.compose(zeros, zeros, torch.zeros_like(z), z, rgb, K, baseline)
    vv, uu = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    for b in range(B):
        fx, fy, cx, cy = K[b, 0, 0].item(), K[b, 1, 1].item(), K[b, 0, 2].item(), K[b, 1, 2].item()
        zf = z[b, 0].numpy()
        pooled = np.array([[zf[max(0, v - 4):v + 5, max(0, u - 4):u + 5].max() for u in range(W)]
                           for v in range(H)])
        for layer, zl in enumerate([zf, pooled + math.log(2.0)]):
            sl = slice(layer * H * W, (layer + 1) * H * W)
            centre = np.stack([(uu + 0.5 - cx) / fx * zl, (vv + 0.5 - cy) / fy * zl, zl], -1).reshape(-1, 3)
            np.testing.assert_allclose(out["means"][b, sl].numpy(), centre, rtol=1e-12, atol=1e-12)
            s0 = (0.5 * zl / math.sqrt(fx * fy)).reshape(-1, 1).repeat(3, 1)
            np.testing.assert_allclose(out["scales"][b, sl].numpy(), s0, rtol=1e-12)
            np.testing.assert_allclose(out["quats"][b, sl].numpy(), np.tile([1.0, 0, 0, 0], (H * W, 1)), atol=0)
            np.testing.assert_allclose(out["opacities"][b, sl].numpy(), 0.99, rtol=1e-12)
            dc = ((rgb[b].numpy() - 0.5) / C0).reshape(3, -1).T
            np.testing.assert_allclose(out["sh"][b, sl, 0].numpy(), dc, rtol=1e-12, atol=1e-12)
            assert (out["sh"][b, sl, 1:] == 0).all()


def test_back_depth_at_zero_dz_and_pooling_inside_canvas():
    z = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0]], dtype=torch.float64)
    z = z.view(1, 1, 1, 12)
    zb = comp.back_depth(z, torch.zeros_like(z))
    expected = torch.tensor([min(u + 4, 11) + 1.0 for u in range(12)], dtype=torch.float64) + math.log(2.0)
    torch.testing.assert_close(zb[0, 0, 0], expected, rtol=0, atol=1e-12)
    # Negative values show what the pool sees: zero or replicate padding would put 0 / a border value in the
    # window; pooling over the canvas only gives the window's own maximum.
    neg = torch.tensor([[-5.0, -4.0, -3.0, -9.0, -9.0, -9.0, -9.0, -9.0, -9.0, -9.0, -9.0, -7.0]], dtype=torch.float64)
    zb = comp.back_depth(neg.view(1, 1, 1, 12), torch.full((1, 1, 1, 12), -1e4, dtype=torch.float64))
    want = [max(neg[0, max(0, u - 4):u + 5]).item() for u in range(12)]
    torch.testing.assert_close(zb[0, 0, 0], torch.tensor(want, dtype=torch.float64), rtol=0, atol=1e-12)


def test_offset_logits_zero_give_pixel_centres():
    B, H, W = 1, 3, 4
    K = torch.tensor([[[10.0, 0.0, 2.0], [0.0, 10.0, 1.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    m = comp.means(torch.full((B, 1, H, W), 10.0, dtype=torch.float64), torch.zeros(B, 2, H, W, dtype=torch.float64), K)
    # pixel (u, v) -> centre (u + 0.5 - cx, v + 0.5 - cy) * z / f
    assert m[0, 0].tolist() == pytest.approx([(0.5 - 2.0), (0.5 - 1.5), 10.0])
    assert m[0, W * 2 + 3].tolist() == pytest.approx([(3.5 - 2.0), (2.5 - 1.5), 10.0])
    # offsets are bounded to half a pixel
    big = comp.means(torch.ones(B, 1, H, W, dtype=torch.float64), torch.full((B, 2, H, W), 1e4, dtype=torch.float64), K)
    assert big[0, 0, 0].item() == pytest.approx((1.0 - 2.0) / 10.0)


# ---------------------------------------------------------------------------------------------------------
# phi and clamps
# ---------------------------------------------------------------------------------------------------------
def test_phi_value_slope_and_bounds():
    t = torch.zeros((), dtype=torch.float64, requires_grad=True)
    y = comp.phi(t)
    (grad,) = torch.autograd.grad(y, t)
    assert y.item() == pytest.approx(1.0, abs=1e-14)
    assert grad.item() == pytest.approx(1.0, abs=1e-14)
    ts = torch.linspace(-10, 10, 401, dtype=torch.float64)  # beyond |t| ~ 25 float64 rounds to the bounds
    p = comp.phi(ts)
    assert (p > 0.2).all() and (p < 5.0).all() and (p.diff() > 0).all()
    assert comp.phi(torch.tensor([-1e4, 1e4], dtype=torch.float64)).tolist() == pytest.approx([0.2, 5.0])


def test_scale_caps_and_clip():
    H, W = 3, 20
    z = torch.full((1, 1, H, W), 2.0, dtype=torch.float64)
    z[..., 10:] = 4.0  # disparity step between columns 9 and 10: edge pixels at column 9, band = columns 1..17
    K = torch.tensor([[[30.0, 0.0, 10.0], [0.0, 30.0, 1.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    baseline = torch.tensor([0.1], dtype=torch.float64)
    res = torch.zeros(1, 37, H, W, dtype=torch.float64)
    res[:, 3:6] = 1e4
    out = comp.compose(res, res, torch.zeros_like(z), z, torch.zeros(1, 3, H, W, dtype=torch.float64), K, baseline)
    scales = out["scales"][0].view(2, H, W, 3)
    zb = z[0, 0].clone()
    zb[:, 6:] = 4.0  # 9 x 9 max (columns 6..9 see column 10 at most 4 away)
    zb = zb + math.log(2.0)
    front = scales[0] / (0.5 * z[0, 0] / 30.0)[..., None]
    back = scales[1] / (0.5 * zb / 30.0)[..., None]
    assert front[:, 1:18].flatten().tolist() == pytest.approx([4.7288] * (H * 17 * 3), abs=1e-4)
    assert front[:, [0, 18, 19]].flatten().tolist() == pytest.approx([5.0] * (H * 3 * 3), abs=1e-9)
    assert back.flatten().tolist() == pytest.approx([4.8888] * (H * W * 3), abs=1e-4)
    # clip at S_MAX = 3 m and S_MIN = 1e-10 m
    big = comp.scales(torch.full((1, 1, 1, 1), 10.0, dtype=torch.float64), torch.zeros(1, 3, 1, 1, dtype=torch.float64),
                      torch.eye(3, dtype=torch.float64)[None], None)
    assert big.flatten().tolist() == [3.0, 3.0, 3.0]
    tiny = comp.scales(torch.full((1, 1, 1, 1), 0.1, dtype=torch.float64),
                       torch.full((1, 3, 1, 1), -1e4, dtype=torch.float64),
                       torch.diag(torch.tensor([1e12, 1e12, 1.0], dtype=torch.float64))[None], None)
    assert tiny.flatten().tolist() == [1e-10, 1e-10, 1e-10]
    for composer in (True, False):  # s0 = 5e-11 m: below S_MIN before any multiplier
        ds = torch.tensor([-1e4, 0.0, 1e4], dtype=torch.float64).view(1, 3, 1, 1)
        f = torch.diag(torch.tensor([1e10, 1e10, 1.0], dtype=torch.float64))[None]
        s = comp.scales(torch.ones(1, 1, 1, 1, dtype=torch.float64), ds, f, None, composer)[0, 0].tolist()
        assert s[:2] == [1e-10, 1e-10]
        assert s[2] == (pytest.approx(2.5e-10, rel=1e-12) if composer else 3.0)


# ---------------------------------------------------------------------------------------------------------
# Edge band and masks
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("step", [0, 5, 11, 28])
def test_edge_band_on_disparity_step(step):
    H, W = 4, 30
    fx, B = 50.0, 0.2
    disp = torch.full((1, 1, H, W), 20.0, dtype=torch.float64)
    disp[..., step + 1:] = 10.0  # step between columns step and step + 1 (edge pixel: column step)
    z = fx * B / disp
    K = torch.tensor([[[fx, 0.0, 15.0], [0.0, fx, 2.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    band = comp.edge_band(z, K, torch.tensor([B], dtype=torch.float64))
    expected = torch.zeros(1, 1, H, W, dtype=torch.bool)
    expected[..., max(0, step - 8):step + 9] = True
    assert torch.equal(band, expected)
    # a transposed step marks rows; a smooth ramp (2% per pixel) marks nothing
    bandT = comp.edge_band(z.transpose(2, 3).contiguous(), K, torch.tensor([B], dtype=torch.float64))
    assert torch.equal(bandT, expected.transpose(2, 3))
    ramp = (1.0 + 0.02 * torch.arange(W, dtype=torch.float64)).view(1, 1, 1, W).expand(1, 1, H, W)
    assert not comp.edge_band(ramp, K, torch.tensor([B], dtype=torch.float64)).any()


def test_hard_and_soft_edge_masks(inputs64):
    front, back, dz, z, rgb, K, baseline = inputs64
    B, _, H, W = z.shape
    plain = comp.compose(*inputs64)["opacities"]
    band = comp.edge_band(z, K, baseline).reshape(B, H * W).double()
    hard = comp.compose(*inputs64, edge_mask="hard")["opacities"]
    soft = comp.compose(*inputs64, edge_mask="soft")["opacities"]
    n = H * W
    for gated in (hard, soft):
        torch.testing.assert_close(gated[:, :n], plain[:, :n], rtol=0, atol=0)  # the front layer is never gated
    torch.testing.assert_close(hard[:, n:], plain[:, n:] * band, rtol=1e-15, atol=0)
    torch.testing.assert_close(soft[:, n:], plain[:, n:] * (0.3 + 0.7 * band), rtol=1e-15, atol=0)
    assert (hard[:, n:][band == 0] == 0).all() and (band == 0).any() and (band == 1).any()


def test_front_layer_only(inputs64):
    front, back, dz, z, rgb, K, baseline = inputs64
    out = comp.compose(front, None, None, z, rgb, K, baseline, back_layer=False)
    full = comp.compose(*inputs64)
    n = z.shape[2] * z.shape[3]
    for k in out:
        assert out[k].shape[1] == n
        torch.testing.assert_close(out[k], full[k][:, :n], rtol=0, atol=0)


def test_without_composer_zero_residuals():
    """composer=False: plain activations -> pixel-centre means, s0 scales, identity quats, opacity 1/2, zero SH."""
    front, back, dz, z, rgb, K, baseline = make_inputs()
    zeros = torch.zeros_like(front)
    out = comp.compose(zeros, zeros, torch.zeros_like(dz), z, rgb, K, baseline, composer=False)
    ref = comp.compose(zeros, zeros, torch.zeros_like(dz), z, rgb, K, baseline)
    torch.testing.assert_close(out["means"], ref["means"], rtol=0, atol=0)
    torch.testing.assert_close(out["scales"], ref["scales"], rtol=1e-15, atol=0)
    assert (out["quats"] == torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)).all()
    assert (out["opacities"] == 0.5).all() and (out["sh"] == 0).all()


def test_quaternion_zero_vector_falls_back_to_identity():
    dq = torch.zeros(1, 4, 1, 2, dtype=torch.float64)
    dq[0, 0, 0, 1] = -10.0  # (1,0,0,0) + 0.1 * (-10,0,0,0) = 0
    q = comp.quats(dq)
    assert q[0].tolist() == [[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]
    assert comp.quats(torch.zeros(1, 4, 1, 1), composer=False)[0, 0].tolist() == [1.0, 0.0, 0.0, 0.0]


# ---------------------------------------------------------------------------------------------------------
# Gradients, dtypes, errors
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("options", OPTIONS, ids=[str(o) or "default" for o in OPTIONS])
def test_gradients_finite_for_extreme_inputs(dtype, options):
    front, back, dz, z, rgb, K, baseline = make_inputs(H=5, W=12, dtype=dtype)
    g = torch.Generator().manual_seed(1)
    sign = lambda t: torch.where(torch.rand(t.shape, generator=g) < 0.5, -1.0, 1.0).to(dtype)  # noqa: E731
    front, back, dz = 1e4 * sign(front), 1e4 * sign(back), 1e4 * sign(dz)
    front[:, 6:10, 0, 0] = 0.0  # a zero quaternion residual (no composer: zero vector)
    back[:, 6:10, 0, 0] = torch.tensor([-10.0, 0.0, 0.0, 0.0], dtype=dtype)  # composer: zero vector
    z = z.clone()
    z[:, :, :2] = 1e-6  # tiny depths
    leaves = [t.clone().requires_grad_(True) for t in (front, back, dz, z, rgb)]
    out = comp.compose(*leaves, K, baseline, **options)
    for k, v in out.items():
        assert v.dtype == dtype and torch.isfinite(v).all(), k
    loss = sum((v * torch.randn(v.shape, generator=g, dtype=dtype)).sum() for v in out.values())
    loss.backward()
    for name, t in zip(("front", "back", "dz", "z", "rgb"), leaves):
        unused = (options.get("back_layer") is False and name in ("back", "dz")) or (
            options.get("composer") is False and name == "rgb")  # no reference-colour base without composer
        if unused:
            assert t.grad is None
            continue
        assert t.grad is not None and torch.isfinite(t.grad).all(), name


def test_bad_input_names_the_field(inputs64):
    front, back, dz, z, rgb, K, baseline = inputs64
    with pytest.raises(ValueError, match="rgb"):
        comp.compose(front, back, dz, z, rgb[:, :2], K, baseline)
    with pytest.raises(ValueError, match="front"):
        comp.compose(front[:, :36], back, dz, z, rgb, K, baseline)
    with pytest.raises(ValueError, match="dz"):
        comp.compose(front, back, dz[:, :, :3], z, rgb, K, baseline)
    with pytest.raises(ValueError, match="edge_mask"):
        comp.compose(*inputs64, edge_mask="blurry")
    with pytest.raises(ValueError, match="back_layer"):
        comp.compose(*inputs64, edge_mask="hard", back_layer=False)


def test_constants_are_the_papers():
    assert (comp.S_MIN, comp.S_MAX, comp.KAPPA, comp.R_QUAT, comp.ALPHA0) == (1e-10, 3.0, 0.5, 0.1, 0.99)
    assert (comp.S_CAP_FRONT_EDGE, comp.S_CAP_BACK, comp.EDGE_THRESHOLD, comp.EDGE_DILATION) == (0.3, 0.5, 0.05, 8)
    assert (comp.BACK_POOL, comp.SOFT_BETA, comp.Z_MIN, comp.Z_MAX) == (9, 0.3, 0.1, 10.0)
    assert comp.C0 == pytest.approx(1.0 / (2.0 * math.sqrt(math.pi)), rel=1e-15)


@pytest.mark.parametrize("options", OPTIONS, ids=[str(o) or "default" for o in OPTIONS])
def test_device_follows_inputs(options):
    """On the meta device any tensor the composer made on the CPU would raise: every tensor follows the inputs."""
    out = comp.compose(*[t.to("meta") for t in make_inputs(dtype=torch.float32)], **options)
    assert all(v.device.type == "meta" and v.dtype == torch.float32 for v in out.values())


@pytest.mark.parametrize("options", OPTIONS, ids=[str(o) or "default" for o in OPTIONS])
def test_backward_keeps_no_view_of_the_branches(options):
    """What the composer keeps for the backward holds none of the 37-channel branch tensors' memory: the model
    passes float32 copies of its bf16 branches, which would otherwise stay alive until the backward (at the
    paper's batch 375 MiB a layer, where the backward needs 30 MiB of it)."""
    front, back, dz, z, rgb, K, baseline = make_inputs(dtype=torch.float32)
    front, back, dz = (t.clone().requires_grad_() for t in (front, back, dz))
    branches = {front.untyped_storage().data_ptr(), back.untyped_storage().data_ptr()}
    kept = []

    def pack(t: torch.Tensor) -> torch.Tensor:
        kept.append(t.untyped_storage().data_ptr())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = comp.compose(front, back, dz, z, rgb, K, baseline, **options)
    assert kept and not branches & set(kept)
    sum(v.sum() for v in out.values()).backward()  # and the backward still runs on what was kept
    assert front.grad is not None and torch.isfinite(front.grad).all()


def test_half_precision_branches_are_composed_in_float32(inputs64):
    """bf16 branches (the predictor's under autocast) give float32 attributes equal to those of their values in
    float32 (off CUDA: the PyTorch path)."""
    front, back, dz, z, rgb, K, baseline = make_inputs(dtype=torch.float32)
    front16, back16 = front.to(torch.bfloat16), back.to(torch.bfloat16)
    got = comp.compose(front16, back16, dz, z, rgb, K, baseline)
    want = comp.compose(front16.float(), back16.float(), dz, z, rgb, K, baseline)
    for k in want:
        assert got[k].dtype == torch.float32
        torch.testing.assert_close(got[k], want[k], rtol=0, atol=0)


@pytest.mark.parametrize("options", OPTIONS, ids=[str(o) or "default" for o in OPTIONS])
def test_composes_in_float32_under_bf16_autocast(options):
    """Training runs the model under bf16 autocast; the composer still works in float32 (its rays were a batched
    matrix product, which autocast would run in bf16: pixel coordinates of 256 to 512 rounded to even numbers)."""
    inputs = make_inputs(H=5, W=300, dtype=torch.float32)
    want = comp.compose(*inputs, **options)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = comp.compose(*inputs, **options)
    for k in want:
        assert got[k].dtype == torch.float32
        torch.testing.assert_close(got[k], want[k], rtol=0, atol=0, msg=k)
