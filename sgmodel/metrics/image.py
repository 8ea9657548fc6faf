"""Image metrics of the feed-forward 3DGS literature (SPEC section 7 "Metrics"): PSNR, SSIM, LPIPS-VGG.

Images are [..., 3, H, W] in [0, 1] (any leading dims, e.g. [B, T]); masks are [..., 1, H, W] bool
(True = valid pixel). Every function returns one value per image, shape [...], so callers average over
targets themselves. Metric functions clip both images to [0, 1] first (the renderer's colours can leave
it); ``ssim_map`` does not clip, so that ``1 - SSIM`` can serve as a differentiable loss.

- PSNR: ``10 log10(1 / MSE)`` with data range 1, MSE over channels and pixels (valid pixels with a mask).
  Identical images give +inf.
- SSIM: exactly ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1, channel_axis=...)``: an 11-tap Gaussian window
  (sigma 1.5, truncated at 3.5 sigma, as scipy.ndimage), ``reflect`` boundary (scipy's: the edge pixel is
  repeated, d c b a | a b c d), K1 = 0.01, K2 = 0.03, population covariances. Without a mask the value
  is skimage's: the SSIM map averaged over channels and over pixels at least 5 px from the border (the
  window radius). With a mask it is the full map (borders included, as skimage's ``full=True``) averaged
  over valid pixels and channels. Images with H or W below 11 (the window) raise ``ValueError``, as
  skimage does.
- LPIPS: ``sgmodel.metrics.lpips.LPIPS`` on inputs scaled to [-1, 1]; without a mask the layer maps are
  averaged spatially (``lpips`` default), with a mask the per-pixel map (``spatial=True``) is averaged
  over valid pixels.
A mask with no valid pixel gives NaN for that image (0 / 0: no value is defined); callers leave such images
out of their means and count them (``has_valid_pixel``), so that one empty mask does not make a mean NaN.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from scenesplat_stereo.common.measure import psnr_from_mse
from sgmodel.kernels import triton_installed
from sgmodel.metrics.lpips import LPIPS

#: SSIM constants of Wang et al. 2004 as skimage uses them (SPEC section 7 "Metrics").
SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
#: window radius as scipy.ndimage computes it: int(truncate * sigma + 0.5) = 5, window 11.
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)
SSIM_WINDOW = 2 * SSIM_RADIUS + 1


def _check(pred: Tensor, target: Tensor, mask: Tensor | None) -> None:
    if pred.shape != target.shape or pred.dim() < 3 or pred.shape[-3] != 3:
        raise ValueError(f"metrics: images must be [..., 3, H, W] of one shape, got {tuple(pred.shape)} "
                         f"and {tuple(target.shape)}")
    if mask is not None:
        want = (*pred.shape[:-3], 1, *pred.shape[-2:])
        if tuple(mask.shape) != want or mask.dtype != torch.bool:
            raise ValueError(f"metrics: mask must be bool {want}, got {mask.dtype} {tuple(mask.shape)}")


def _masked_mean(values: Tensor, mask: Tensor | None) -> Tensor:
    """Mean of [..., C, H, W] over C, H, W; with a mask [..., 1, H, W] over valid pixels only."""
    if mask is None:
        return values.mean(dim=(-3, -2, -1))
    w = mask.to(values.dtype).expand_as(values)
    return (values * w).sum(dim=(-3, -2, -1)) / w.sum(dim=(-3, -2, -1))


def has_valid_pixel(mask: Tensor) -> Tensor:
    """[...] bool per mask [..., 1, H, W]: whether it has a valid pixel, i.e. whether the masked metrics of its
    image are defined (they are NaN where it has none)."""
    return mask.flatten(-3).any(dim=-1)


def psnr(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """PSNR in dB per image [...], images clipped to [0, 1], data range 1."""
    _check(pred, target, mask)
    return psnr_from_mse(_masked_mean((pred.clamp(0, 1) - target.clamp(0, 1)).pow(2), mask))


@functools.cache
def _gaussian_window(dtype: torch.dtype, device: torch.device) -> Tensor:
    """The window's 2r + 1 taps, made once per dtype and device (not copied to the GPU at every call: a copy
    from pageable memory waits for the stream). Callers only read it."""
    x = torch.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return (w / w.sum()).to(dtype=dtype, device=device)


def _symmetric_index(n: int, r: int, device: torch.device) -> Tensor:
    """Indices of a length-n axis padded by r on each side with scipy's ``reflect`` (edge repeated);
    valid for r <= n."""
    i = torch.arange(-r, n + r, device=device)
    return torch.where(i < 0, -i - 1, torch.where(i >= n, 2 * n - 1 - i, i))


def _gaussian_filter(x: Tensor, border: bool = True) -> Tensor:
    """scipy.ndimage.gaussian_filter(sigma 1.5, truncate 3.5, mode 'reflect') over the last two axes of
    [N, C, H, W], separable, per channel; ``border=False``: only the outputs whose window lies inside the
    image, [N, C, H - 2r, W - 2r], which read no padding (none is made)."""
    n, c, h, w = x.shape
    r = SSIM_RADIUS
    k = _gaussian_window(x.dtype, x.device)
    if border:
        x = x.index_select(-2, _symmetric_index(h, r, x.device)).index_select(-1, _symmetric_index(w, r, x.device))
    x = F.conv2d(x, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return F.conv2d(x, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)


def _moments(x: Tensor, y: Tensor, border: bool) -> Tensor:
    """The filtered moments [ux, uy, E[xx], E[yy], E[xy]] of x, y [N, 3, H, W] ([N, 15, ...], three channels
    each; ``border`` as ``_gaussian_filter``)."""
    return _gaussian_filter(torch.cat([x, y, x * x, y * y, x * y], dim=1), border)


def _ssim_terms(f: Tensor) -> tuple[Tensor, ...]:
    """(S, A, B, C, D) of the filtered moments f = [ux, uy, E[xx], E[yy], E[xy]] ([N, 15, h, w], three
    channels each): S = A B / (C D), A = 2 ux uy + c1, B = 2 cov + c2, C = ux^2 + uy^2 + c1, D = var_x +
    var_y + c2 (data range 1)."""
    ux, uy, uxx, uyy, uxy = f.split(3, dim=1)
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    a, b = 2 * ux * uy + c1, 2 * (uxy - ux * uy) + c2
    c, d = ux * ux + uy * uy + c1, (uxx - ux * ux) + (uyy - uy * uy) + c2
    return a * b / (c * d), a, b, c, d


class _InteriorSSIM(torch.autograd.Function):
    """The interior SSIM map of x, y [N, 3, H, W] with a hand-written backward: with the five filtered
    moments of the forward kept, dS/d(ux, E[xx], E[xy]) per pixel in closed form (no division by A or B,
    which may vanish: dS/dux = 2 uy (B - A) / (C D) - 2 ux S (1/C - 1/D), dS/dE[xx] = -S/D,
    dS/dE[xy] = 2 A / (C D)), filtered back through the (symmetric) window into x: dx = G'(dS/dux) +
    2 x G'(dS/dE[xx]) + y G'(dS/dE[xy]), G' the window zero-padded to the full image; y's the same with
    the roles swapped. Autograd through the forward instead keeps a dozen maps and filters the gradient of
    all five moments, y's too (1.6 ms of a training step on an H100)."""

    @staticmethod
    def forward(ctx, x: Tensor, y: Tensor) -> Tensor:
        f = _moments(x, y, border=False)
        ctx.save_for_backward(x, y, f)
        return _ssim_terms(f)[0]

    @staticmethod
    def backward(ctx, grad: Tensor):
        x, y, f = ctx.saved_tensors
        need_x, need_y = ctx.needs_input_grad
        ux, uy = f[:, 0:3], f[:, 3:6]
        s, a, b, c, d = _ssim_terms(f)
        cd = c * d
        gs = grad * s
        shift = 1 / c - 1 / d
        maps = [grad * 2 * a / cd, -gs / d]  # dS/dE[xy], dS/dE[xx] (= dS/dE[yy]) times the incoming gradient
        if need_x:
            maps.append(grad * 2 * uy * (b - a) / cd - 2 * ux * gs * shift)
        if need_y:
            maps.append(grad * 2 * ux * (b - a) / cd - 2 * uy * gs * shift)
        back = _full_filter(torch.cat(maps, dim=1)).split(3, dim=1)
        dx = back[2] + 2 * x * back[1] + y * back[0] if need_x else None
        dy = back[-1] + 2 * y * back[1] + x * back[0] if need_y else None
        return dx, dy


class _KernelSSIM(torch.autograd.Function):
    """``_InteriorSSIM`` for float32 CUDA images in two Triton kernels (``sgmodel.kernels.ssim``): the forward
    filters the five moments and writes S with the derivative maps the backward needs, the backward filters
    them back and combines them with x and y, reading and writing the images in their own layout (in a
    training step on an H100: 2.7 ms of kernels, forward and backward, where ``_InteriorSSIM``'s depthwise
    convolutions alone took 6.7; the loss stage 7.2 -> 2.0 ms; 1.3 GiB less peak memory)."""

    @staticmethod
    def forward(ctx, x: Tensor, y: Tensor) -> Tensor:
        from sgmodel.kernels import ssim as ssim_kernels

        window = _gaussian_window(torch.float32, x.device)
        s, maps = ssim_kernels.forward(x, y, window, SSIM_K1 ** 2, SSIM_K2 ** 2, *ctx.needs_input_grad)
        ctx.save_for_backward(x, y, maps, window)
        return s

    @staticmethod
    def backward(ctx, grad: Tensor):
        from sgmodel.kernels import ssim as ssim_kernels

        return ssim_kernels.backward(grad, *ctx.saved_tensors, *ctx.needs_input_grad)


def _full_filter(g: Tensor) -> Tensor:
    """The transpose of ``_gaussian_filter(..., border=False)``: [N, C, h, w] -> [N, C, h + 2r, w + 2r], the
    (symmetric) window over the zero-padded maps."""
    c, r = g.shape[1], SSIM_RADIUS
    k = _gaussian_window(g.dtype, g.device)
    g = F.conv2d(g, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), padding=(2 * r, 0), groups=c)
    return F.conv2d(g, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), padding=(0, 2 * r), groups=c)


def ssim_map(pred: Tensor, target: Tensor, border: bool = True) -> Tensor:
    """SSIM map [..., 3, H, W] (skimage's ``full=True`` map per channel); no clipping, differentiable.
    ``border=False``: only its interior [..., 3, H - 2r, W - 2r] (pixels at least r = ``SSIM_RADIUS`` from
    the border, what the SSIM value averages without a mask), the same numbers without filtering the
    reflect-padded border, with a hand-written backward (``_InteriorSSIM``; the training loss's SSIM
    term), in Triton kernels for float32 CUDA images (``_KernelSSIM``)."""
    _check(pred, target, None)
    h, w = pred.shape[-2:]
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(f"SSIM: image {h}x{w} is smaller than the {SSIM_WINDOW}x{SSIM_WINDOW} Gaussian "
                         f"window (skimage raises too)")
    lead = pred.shape[:-3]
    x = pred.reshape(-1, 3, h, w)
    y = target.reshape(-1, 3, h, w)
    if border:
        s = _ssim_terms(_moments(x, y, border=True))[0]
    elif x.is_cuda and x.dtype == y.dtype == torch.float32 and triton_installed():
        s = _KernelSSIM.apply(x, y)
    else:
        s = _InteriorSSIM.apply(x, y)
    return s.reshape(*lead, *s.shape[-3:])


def ssim(pred: Tensor, target: Tensor, mask: Tensor | None = None, clip: bool = True) -> Tensor:
    """SSIM per image [...] as skimage (see the module docstring for the masked variant)."""
    _check(pred, target, mask)
    if clip:
        pred, target = pred.clamp(0, 1), target.clamp(0, 1)
    if mask is None:
        return ssim_map(pred, target, border=False).mean(dim=(-3, -2, -1))
    return _masked_mean(ssim_map(pred, target), mask)


def lpips(net: LPIPS, pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """LPIPS-VGG per image [...], images clipped to [0, 1] then scaled to [-1, 1] inside ``net``."""
    _check(pred, target, mask)
    pred, target = pred.clamp(0, 1), target.clamp(0, 1)
    if mask is None:
        return net(pred, target)
    return _masked_mean(net.per_pixel(pred, target), mask)


@torch.no_grad()
def image_metrics(pred: Tensor, target: Tensor, mask: Tensor | None = None,
                  lpips_net: LPIPS | None = None) -> dict[str, Tensor]:
    """``psnr``, ``ssim`` and, when ``lpips_net`` is given, ``lpips``: each [...] per image."""
    out = {"psnr": psnr(pred, target, mask), "ssim": ssim(pred, target, mask)}
    if lpips_net is not None:
        out["lpips"] = lpips(lpips_net, pred, target, mask)
    return out

