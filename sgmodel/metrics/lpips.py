"""LPIPS-VGG v0.1 (Zhang et al. 2018): the perceptual term of the objective and the LPIPS metric.

Written here because torchvision (and so the ``lpips`` package, which imports it) cannot be imported
beside the CPU torch wheel. Two weight files, both loaded strictly:

- VGG16's ImageNet convolutions in torchvision's layout (``features.N.weight`` / ``features.N.bias``,
  the file ``vgg16-397923af.pth``), from ``--lpips-vgg PATH`` or torch's hub cache
  (``$TORCH_HOME/hub/checkpoints``, default ``~/.cache/torch/hub/checkpoints``). They cannot be downloaded
  here: without them ``create_lpips`` returns None and the objective falls back (``sgmodel.train.losses``).
- The five 1x1 linear layers of LPIPS v0.1 (``lin0..lin4.model.1.weight``, shipped in the ``lpips`` wheel),
  through ``sgmodel.weights.resolve("lpips-vgg")`` (``sgmodel weights fetch lpips-vgg``).

Computation, per image pair: inputs in [0, 1] are mapped to [-1, 1] (``2x - 1``; the literature's
convention) unless ``zero_one=False`` says they already are; LPIPS's scaling layer ``(x - shift) / scale``;
VGG16 up to each of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; each feature map unit-normalised over
channels (``f / (||f||_2 + 1e-10)``); squared difference; the layer's 1x1 linear weights summed over
channels; the spatial mean per layer, summed over the five layers. ``per_pixel`` instead upsamples each
layer's map bilinearly (half-pixel centres) to the input size and sums them, as ``lpips``'s
``spatial=True``. The module is frozen: eval mode always, no parameter requires a gradient (gradients
still reach the inputs).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sgmodel.kernels import triton_kernels_run
from sgmodel.weights import WeightsError, resolve, sha256_file

#: torchvision's file name for the ImageNet VGG16 weights; its 8 hex digits are the sha256 prefix.
VGG16_FILENAME = "vgg16-397923af.pth"
#: VGG16 configuration "D" (Simonyan & Zisserman 2015): channels per conv, "M" = 2x2 max-pool.
_VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
#: indices in ``features`` of the ReLUs LPIPS taps: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
TAPS = (3, 8, 15, 22, 29)
#: channels of those five feature maps.
CHANNELS = (64, 128, 256, 512, 512)
#: LPIPS v0.1 scaling layer (``lpips.ScalingLayer``): input (x - shift) / scale, x in [-1, 1].
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
#: epsilon of LPIPS's channel normalisation ``f / (||f|| + eps)``.
_NORM_EPS = 1e-10
#: the widest features ``tap_distance`` sends to the Triton kernels (a program holds every channel of its pixels).
_KERNEL_MAX_CHANNELS = 1024


class VGG16Trunk(nn.Module):
    """VGG16's ``features`` up to relu5_3 (index 29), indexed as torchvision's so that its state dict keys
    are ``features.N.weight`` / ``features.N.bias`` (the last pool, index 30, has no weights)."""

    def __init__(self):
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 3
        for v in _VGG16_CFG:
            if v == "M":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                layers += [nn.Conv2d(c_in, v, kernel_size=3, padding=1), nn.ReLU(inplace=False)]
                c_in = v
        self.features = nn.Sequential(*layers)


def find_vgg16_weights(path: str | os.PathLike | None = None) -> Path | None:
    """The VGG16 weight file: ``path`` when given (must exist, else ``WeightsError`` naming
    ``--lpips-vgg``), else ``vgg16-397923af.pth`` in torch's hub cache, else None."""
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise WeightsError(f"--lpips-vgg {p}: no such file")
        return p
    p = Path(torch.hub.get_dir()) / "checkpoints" / VGG16_FILENAME
    return p if p.is_file() else None


def load_vgg16_state(path: str | os.PathLike) -> dict[str, Tensor]:
    """The ``features.*`` tensors of a torchvision-format VGG16 file (the ImageNet classifier head,
    ``classifier.*``, is dropped: LPIPS does not use it). A file named ``vgg16-<8 hex>.pth`` must have
    that sha256 prefix, as torchvision checks. Any other key is left in, so strict loading names it."""
    p = Path(path)
    m = re.fullmatch(r"vgg16-([0-9a-f]{8})\.pth", p.name)
    if m and not sha256_file(p).startswith(m.group(1)):
        raise WeightsError(f"{p}: sha256 does not start with {m.group(1)} (truncated or corrupt download?)")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file is reported the same way
        raise WeightsError(f"{p}: not a readable torch state dict ({e})") from e
    if not isinstance(state, dict):
        raise WeightsError(f"{p}: expected a state dict, got {type(state).__name__}")
    return {k: v for k, v in state.items() if not k.startswith("classifier.")}


def load_lpips_linear(path: str | os.PathLike) -> list[Tensor]:
    """The five LPIPS v0.1 linear weights ``lin{i}.model.1.weight`` [1, C_i, 1, 1], checked strictly."""
    p = Path(path)
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file is reported the same way
        raise WeightsError(f"{p}: not a readable torch state dict ({e})") from e
    expected = [f"lin{i}.model.1.weight" for i in range(len(CHANNELS))]
    if sorted(state) != sorted(expected):
        raise WeightsError(f"{p}: keys {sorted(state)}, expected {expected}")
    out = []
    for key, c in zip(expected, CHANNELS):
        w = state[key]
        if tuple(w.shape) != (1, c, 1, 1):
            raise WeightsError(f"{p}: {key} has shape {tuple(w.shape)}, expected (1, {c}, 1, 1)")
        out.append(w.float())
    return out


class _TapDistance(torch.autograd.Function):
    """sum_c w_c (a_c / (|a| + eps) - b_c / (|b| + eps))^2 per pixel, with a hand-written backward.

    Left to autograd, the normalisations, the difference, its square and the weighting each keep or make
    a float32 copy of the layer's feature maps (128 x 64 x 256 x 256 at the first tap in a training
    step), and their backward as many again. Here the forward keeps one (the difference) and the
    backward makes about three per side. With n = |f| + eps, u = f / n and h = dd/du:
    dd/df = (h - f (h . f) / (n |f|)) / n, taking the second term as 0 where |f| = 0 (f is 0 there; the
    convention of ``torch.linalg.vector_norm``'s gradient)."""

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, weight: Tensor) -> Tensor:
        with torch.autocast(a.device.type, enabled=False):
            accumulate = torch.promote_types(a.dtype, torch.float32)
            norms = [torch.linalg.vector_norm(f, dim=1, keepdim=True, dtype=accumulate) for f in (a, b)]
            diff = a / (norms[0] + _NORM_EPS)
            diff.addcdiv_(b, norms[1] + _NORM_EPS, value=-1.0)
            out = diff.square().mul_(weight).sum(dim=1, keepdim=True)
        # a side's features are kept only when its gradient is wanted (not the targets' in training)
        ctx.save_for_backward(*(f if ctx.needs_input_grad[i] else None for i, f in enumerate((a, b))), weight, diff,
                              *norms)
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        a, b, weight, diff, norm_a, norm_b = ctx.saved_tensors
        grads = [None, None, None]
        with torch.autocast(grad.device.type, enabled=False):
            h = weight * diff  # dd/du_a / 2 = w (u_a - u_b) = -dd/du_b / 2
            for i, (f, norm, sign) in enumerate(((a, norm_a, 2.0), (b, norm_b, -2.0))):
                if not ctx.needs_input_grad[i]:
                    continue
                n = norm + _NORM_EPS
                along = (h * f).sum(dim=1, keepdim=True) / (n * torch.where(norm > 0, norm, 1.0))
                g = torch.addcmul(h, f, along, value=-1.0).mul_(grad * sign / n)
                grads[i] = g.to(f.dtype)
        return tuple(grads)


class _KernelTapDistance(torch.autograd.Function):
    """``_TapDistance`` for CUDA features in two Triton kernels (``sgmodel.kernels.lpips_tap``): the forward reads
    each side once and keeps the two norms per pixel, the backward recomputes the difference from the
    features; no float32 copy of a feature map is made or kept."""

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, weight: Tensor) -> Tensor:
        from sgmodel.kernels import lpips_tap as lpips_kernels

        w = weight.reshape(-1).float().contiguous()
        d, norm_a, norm_b = lpips_kernels.forward(a, b, w, _NORM_EPS)
        if any(ctx.needs_input_grad[:2]):  # both sides' features: the difference is recomputed from them
            ctx.save_for_backward(a, b, w, norm_a, norm_b)
        return d

    @staticmethod
    def backward(ctx, grad: Tensor):
        from sgmodel.kernels import lpips_tap as lpips_kernels

        a, b, w, norm_a, norm_b = ctx.saved_tensors
        da, db = lpips_kernels.backward(grad, a, b, w, norm_a, norm_b, _NORM_EPS, *ctx.needs_input_grad[:2])
        return da, db, None


def _kernel_runs(a: Tensor, b: Tensor) -> bool:
    """Whether ``tap_distance`` runs the Triton kernels: features the kernels take (``layers.triton_kernels_run``)
    of one dtype, at most ``_KERNEL_MAX_CHANNELS`` channels."""
    return triton_kernels_run(a) and a.dtype == b.dtype and a.shape[1] <= _KERNEL_MAX_CHANNELS


def tap_distance(a: Tensor, b: Tensor, weight: Tensor) -> Tensor:
    """LPIPS's distance map of one tap: raw features a, b [N, C, h, w] (any float dtype), linear weights
    [1, C, 1, 1] -> [N, 1, h, w] in float32 (float64 for float64 inputs): each side unit-normalised over
    channels (|f| + 1e-10), the squared difference weighted and summed over channels. On CUDA in Triton
    kernels (``_KernelTapDistance``), elsewhere ``_TapDistance``."""
    weight = weight.to(torch.promote_types(weight.dtype, torch.float32))
    return (_KernelTapDistance if _kernel_runs(a, b) else _TapDistance).apply(a, b, weight)


class LPIPS(nn.Module):
    """LPIPS-VGG v0.1, frozen. Images [..., 3, H, W]; values per image [...] (lower = more similar)."""

    def __init__(self, vgg_state: dict[str, Tensor], linear: list[Tensor], vgg_sha256: str | None = None):
        super().__init__()
        self.vgg = VGG16Trunk()
        self.vgg.load_state_dict(vgg_state, strict=True)
        for i, w in enumerate(linear):
            self.register_buffer(f"lin{i}", w.reshape(1, CHANNELS[i], 1, 1).clone())
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.vgg_sha256 = vgg_sha256
        self._trunk = self._trunk_eager  # compile_trunk() replaces it
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "LPIPS":
        """Frozen: stays in eval mode whatever the caller asks."""
        return super().train(False)

    def compile_trunk(self) -> "LPIPS":
        """From now on run the scaling layer and VGG16 up to relu5_3 through ``torch.compile`` (inductor,
        static shapes): for the bf16 training loss on CUDA (``sgmodel train``'s default there; the step with
        the LPIPS term about 7% faster on an H100, for about 15 s of compilation per process and image
        shape: docs/benchmarks.md). The same operations; bf16 results differ by rounding only."""
        self._trunk = torch.compile(self._trunk_eager, dynamic=False)
        return self

    def taps(self, x: Tensor, zero_one: bool = True) -> list[Tensor]:
        """The raw VGG16 features [N, C_l, h_l, w_l] of images [N, 3, H, W] at the LPIPS taps (relu1_2 ...
        relu5_3; ``tap_distance`` normalises them)."""
        if x.is_cuda and torch.is_autocast_enabled("cuda"):
            # the bf16 training loss: channels-last convolutions, without cuDNN's layout conversions
            # (loss + backward 182.5 -> 162.6 ms with the norm below, H100, 128 pairs at 256x256)
            x = x.contiguous(memory_format=torch.channels_last)
        return self._trunk(x, zero_one)

    def _trunk_eager(self, x: Tensor, zero_one: bool) -> list[Tensor]:
        if zero_one:
            x = 2 * x - 1
        x = (x - self.shift) / self.scale
        taps = []
        for k, layer in enumerate(self.vgg.features):
            x = layer(x)
            if k == TAPS[len(taps)]:
                taps.append(x)
                if len(taps) == len(TAPS):
                    break
        return taps

    def layer_maps(self, a: Tensor, b: Tensor, zero_one: bool = True) -> list[Tensor]:
        """Per-layer distance maps [N, 1, h_l, w_l] (N = product of the leading dims), before averaging.
        An image side that needs no gradient (the targets in training) runs without autograd."""
        if a.shape != b.shape or a.dim() < 3 or a.shape[-3] != 3:
            raise ValueError(f"LPIPS: images must be [..., 3, H, W] of one shape, got {tuple(a.shape)} "
                             f"and {tuple(b.shape)}")
        n = a.shape[:-3].numel()
        sides = []
        for x in (a, b):
            with torch.set_grad_enabled(torch.is_grad_enabled() and x.requires_grad):
                sides.append(self.taps(x.reshape(n, *x.shape[-3:]), zero_one))
        return [tap_distance(fa, fb, getattr(self, f"lin{i}")) for i, (fa, fb) in enumerate(zip(*sides))]

    def forward(self, a: Tensor, b: Tensor, zero_one: bool = True) -> Tensor:
        """LPIPS per image pair, [...]: each layer's map averaged spatially, summed over layers."""
        maps = self.layer_maps(a, b, zero_one)
        return sum(m.mean(dim=(1, 2, 3)) for m in maps).reshape(a.shape[:-3])

    def per_pixel(self, a: Tensor, b: Tensor, zero_one: bool = True) -> Tensor:
        """LPIPS map [..., 1, H, W]: each layer's map upsampled bilinearly (align_corners=False) to the
        input size, summed over layers (``lpips`` with ``spatial=True``)."""
        size = a.shape[-2:]
        maps = self.layer_maps(a, b, zero_one)
        up = sum(F.interpolate(m, size=size, mode="bilinear", align_corners=False) for m in maps)
        return up.reshape(*a.shape[:-3], 1, *size)


def create_lpips(vgg_path: str | os.PathLike | None = None, lin_path: str | os.PathLike | None = None,
                 device: str | torch.device = "cpu") -> LPIPS | None:
    """LPIPS-VGG on ``device``, or None when no VGG16 weights are given and none are in torch's hub cache.

    ``vgg_path`` given but missing, an unreadable or mismatching file, or the linear layers neither given
    (``lin_path``) nor cached raise ``WeightsError`` with what to do."""
    vgg = find_vgg16_weights(vgg_path)
    if vgg is None:
        return None
    linear = load_lpips_linear(resolve("lpips-vgg", lin_path, flag="--lpips-linear"))
    state = load_vgg16_state(vgg)
    try:
        net = LPIPS(state, linear, vgg_sha256=sha256_file(vgg))
    except RuntimeError as e:
        raise WeightsError(f"{vgg}: not torchvision's VGG16 layout: {e}") from e
    return net.to(device)


def random_lpips(device: str | torch.device = "cpu", seed: int = 0) -> LPIPS:
    """LPIPS-VGG with randomly initialised VGG16 convolutions (PyTorch's default initialisation, seeded)
    and the real v0.1 linear layers (``sgmodel weights fetch lpips-vgg``): for timing the LPIPS term where
    the ImageNet file is absent (``sgmodel bench train --lpips-random-vgg``); its values mean nothing.
    ``vgg_sha256`` is "random"."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        state = VGG16Trunk().state_dict()
    return LPIPS(state, load_lpips_linear(resolve("lpips-vgg")), vgg_sha256="random").to(device)


def vgg16_missing_message() -> str:
    """Why LPIPS is unavailable and how to provide it (for the first log lines and config.json)."""
    where = Path(torch.hub.get_dir()) / "checkpoints" / VGG16_FILENAME
    return (f"no VGG16 weights: {where} is absent and --lpips-vgg was not given "
            f"(torchvision's ImageNet {VGG16_FILENAME})")
