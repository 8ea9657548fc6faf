"""Triton kernels of the interior SSIM map and its gradient (``sgmodel.metrics.image.ssim_map(..., border=False)``,
the training loss's SSIM term) for float32 CUDA images of any strides.

Imported only on CUDA with Triton present; elsewhere ``metrics._InteriorSSIM`` computes the same map with
PyTorch's depthwise convolutions, which is also the float64 reference the kernels are tested against
(tests/sgmodel/kernels/test_ssim_kernels.py). Conventions as ``_InteriorSSIM``'s: x, y [N, C, H, W]; the interior map
[N, C, h, w] with h = H - 2r, w = W - 2r (r = 5), the window's taps g[0..2r]; interior pixel (i, j) reads
image pixels (i + t, j + l) with weight g[t] g[l].

Forward: one program per tile of BH x BW interior pixels of one image channel. It walks the BH + 2r image
rows the tile's windows cover; on each row it filters the five moments (x, y, x^2, y^2, xy) along the row
(the 11 shifted columns are cached loads) and adds the filtered row, weighted by the tap g[t] each output
row gives it, into five accumulators. From the filtered moments it writes S and, when an input needs a
gradient, the derivatives of S by the moments in ``metrics._InteriorSSIM``'s closed form: dS/dE[xy],
dS/dE[xx] (= dS/dE[yy]), and dS/dux and/or dS/duy.
Backward: one program per tile of image pixels, the window transposed: it walks the interior rows whose
windows reach the tile, filters (incoming gradient x derivative map) along each and accumulates the rows as
the forward does; then dy = G'(g dS/duy) + 2 y G'(g dS/dE[yy]) + x G'(g dS/dE[xy]) (dx with the roles
swapped). In float32 throughout; the moments are summed rows first, the convolutions columns first: the two
agree with float64 within float32 rounding.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

_BH = 16  # rows of a program's tile (each image row it reads is added to these rows with its tap)
_BW = 64  # columns of a program's tile


@triton.jit
def _ssim_forward_kernel(x_ptr, y_ptr, g_ptr, s_ptr, k_ptr, C, H, h, w, map_stride, c1, c2,
                         sxn, sxc, sxh, sxw, syn, syc, syh, syw,
                         R: tl.constexpr, NEED_X: tl.constexpr, NEED_Y: tl.constexpr, Y_SLOT: tl.constexpr,
                         BH: tl.constexpr, BW: tl.constexpr):
    cb, rb, plane = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    n, c = plane // C, plane % C
    xb = x_ptr + n.to(tl.int64) * sxn + c.to(tl.int64) * sxc
    yb = y_ptr + n.to(tl.int64) * syn + c.to(tl.int64) * syc
    rows = rb * BH + tl.arange(0, BH)  # interior rows of the tile
    cols = cb * BW + tl.arange(0, BW)  # interior columns of the tile
    col_ok = cols < w
    ux = tl.zeros((BH, BW), dtype=tl.float32)
    uy = tl.zeros((BH, BW), dtype=tl.float32)
    uxx = tl.zeros((BH, BW), dtype=tl.float32)
    uyy = tl.zeros((BH, BW), dtype=tl.float32)
    uxy = tl.zeros((BH, BW), dtype=tl.float32)
    for t in range(0, BH + 2 * R):
        r = rb * BH + t  # the image row
        ok = col_ok & (r < H)
        hx = tl.zeros((BW,), dtype=tl.float32)
        hy = tl.zeros((BW,), dtype=tl.float32)
        hxx = tl.zeros((BW,), dtype=tl.float32)
        hyy = tl.zeros((BW,), dtype=tl.float32)
        hxy = tl.zeros((BW,), dtype=tl.float32)
        for l in tl.static_range(2 * R + 1):
            gl = tl.load(g_ptr + l)
            xv = tl.load(xb + r * sxh + (cols + l) * sxw, mask=ok, other=0.0)
            yv = tl.load(yb + r * syh + (cols + l) * syw, mask=ok, other=0.0)
            gx, gy = gl * xv, gl * yv
            hx += gx
            hy += gy
            hxx += gx * xv
            hyy += gy * yv
            hxy += gx * yv
        tap = t - tl.arange(0, BH)  # the tap with which each output row reads image row r
        wt = tl.load(g_ptr + tap, mask=(tap >= 0) & (tap <= 2 * R), other=0.0)[:, None]
        ux += wt * hx[None, :]
        uy += wt * hy[None, :]
        uxx += wt * hxx[None, :]
        uyy += wt * hyy[None, :]
        uxy += wt * hxy[None, :]
    a = 2 * ux * uy + c1
    b = 2 * (uxy - ux * uy) + c2
    cc = ux * ux + uy * uy + c1
    d = (uxx - ux * ux) + (uyy - uy * uy) + c2
    s = a * b / (cc * d)
    out = plane.to(tl.int64) * h * w + (rows * w)[:, None] + cols[None, :]
    out_ok = (rows < h)[:, None] & col_ok[None, :]
    tl.store(s_ptr + out, s, mask=out_ok)
    if NEED_X or NEED_Y:
        inv = 1.0 / (cc * d)
        tl.store(k_ptr + out, 2 * a * inv, mask=out_ok)  # dS/dE[xy]
        tl.store(k_ptr + map_stride + out, -s / d, mask=out_ok)  # dS/dE[xx] = dS/dE[yy]
        bma = 2 * (b - a) * inv
        shift = 2 * s * (1.0 / cc - 1.0 / d)
        if NEED_X:
            tl.store(k_ptr + 2 * map_stride + out, uy * bma - ux * shift, mask=out_ok)  # dS/dux
        if NEED_Y:
            tl.store(k_ptr + Y_SLOT * map_stride + out, ux * bma - uy * shift, mask=out_ok)  # dS/duy


@triton.jit
def _ssim_backward_kernel(grad_ptr, k_ptr, x_ptr, y_ptr, g_ptr, dx_ptr, dy_ptr, C, H, W, h, w, map_stride,
                          sgn, sgc, sgh, sgw, sxn, sxc, sxh, sxw, syn, syc, syh, syw,
                          sdxn, sdxc, sdxh, sdxw, sdyn, sdyc, sdyh, sdyw, R: tl.constexpr, NEED_X: tl.constexpr,
                          NEED_Y: tl.constexpr, Y_SLOT: tl.constexpr, BH: tl.constexpr, BW: tl.constexpr):
    cb, rb, plane = tl.program_id(0), tl.program_id(1), tl.program_id(2)
    n, c = plane // C, plane % C
    gb = grad_ptr + n.to(tl.int64) * sgn + c.to(tl.int64) * sgc
    kb = k_ptr + plane.to(tl.int64) * h * w
    rows = rb * BH + tl.arange(0, BH)  # image rows of the tile
    cols = cb * BW + tl.arange(0, BW)  # image columns of the tile
    a_xy = tl.zeros((BH, BW), dtype=tl.float32)
    a_sq = tl.zeros((BH, BW), dtype=tl.float32)
    a_ux = tl.zeros((BH, BW), dtype=tl.float32)
    a_uy = tl.zeros((BH, BW), dtype=tl.float32)
    for t in range(0, BH + 2 * R):
        p = rb * BH - 2 * R + t  # the interior row
        row_ok = (p >= 0) & (p < h)
        h_xy = tl.zeros((BW,), dtype=tl.float32)
        h_sq = tl.zeros((BW,), dtype=tl.float32)
        h_ux = tl.zeros((BW,), dtype=tl.float32)
        h_uy = tl.zeros((BW,), dtype=tl.float32)
        for l in tl.static_range(2 * R + 1):
            q = cols - l  # the interior column whose window reads this image column with tap l
            ok = row_ok & (q >= 0) & (q < w)
            gv = tl.load(g_ptr + l) * tl.load(gb + p * sgh + q * sgw, mask=ok, other=0.0).to(tl.float32)
            at = p * w + q
            h_xy += gv * tl.load(kb + at, mask=ok, other=0.0)
            h_sq += gv * tl.load(kb + map_stride + at, mask=ok, other=0.0)
            if NEED_X:
                h_ux += gv * tl.load(kb + 2 * map_stride + at, mask=ok, other=0.0)
            if NEED_Y:
                h_uy += gv * tl.load(kb + Y_SLOT * map_stride + at, mask=ok, other=0.0)
        tap = rows - p  # the tap with which interior row p reads each image row of the tile
        wt = tl.load(g_ptr + tap, mask=(tap >= 0) & (tap <= 2 * R), other=0.0)[:, None]
        a_xy += wt * h_xy[None, :]
        a_sq += wt * h_sq[None, :]
        if NEED_X:
            a_ux += wt * h_ux[None, :]
        if NEED_Y:
            a_uy += wt * h_uy[None, :]
    ok = (rows < H)[:, None] & (cols < W)[None, :]
    xo = n.to(tl.int64) * sxn + c.to(tl.int64) * sxc + (rows * sxh)[:, None] + (cols * sxw)[None, :]
    yo = n.to(tl.int64) * syn + c.to(tl.int64) * syc + (rows * syh)[:, None] + (cols * syw)[None, :]
    xv = tl.load(x_ptr + xo, mask=ok, other=0.0)
    yv = tl.load(y_ptr + yo, mask=ok, other=0.0)
    if NEED_X:
        dxo = n.to(tl.int64) * sdxn + c.to(tl.int64) * sdxc + (rows * sdxh)[:, None] + (cols * sdxw)[None, :]
        tl.store(dx_ptr + dxo, a_ux + 2 * xv * a_sq + yv * a_xy, mask=ok)
    if NEED_Y:
        dyo = n.to(tl.int64) * sdyn + c.to(tl.int64) * sdyc + (rows * sdyh)[:, None] + (cols * sdyw)[None, :]
        tl.store(dy_ptr + dyo, a_uy + 2 * yv * a_sq + xv * a_xy, mask=ok)


def _grid(rows: int, cols: int, planes: int) -> tuple[int, int, int]:
    return triton.cdiv(cols, _BW), triton.cdiv(rows, _BH), planes


def forward(x: torch.Tensor, y: torch.Tensor, window: torch.Tensor, c1: float, c2: float, need_x: bool,
            need_y: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The interior SSIM map [N, C, h, w] of float32 CUDA images x, y [N, C, H, W] (any strides; ``window``
    the 2r + 1 float32 taps), and the derivative maps the backward reads [k, N, C, h, w] (k = 2 + need_x +
    need_y; empty when neither input needs a gradient)."""
    N, C, H, W = x.shape
    R = (window.numel() - 1) // 2
    h, w = H - 2 * R, W - 2 * R
    s = torch.empty(N, C, h, w, device=x.device, dtype=torch.float32)
    k = torch.empty((2 + need_x + need_y) if need_x or need_y else 0, N, C, h, w, device=x.device,
                    dtype=torch.float32)
    _ssim_forward_kernel[_grid(h, w, N * C)](x, y, window, s, k, C, H, h, w, N * C * h * w, c1, c2, *x.stride(),
                                             *y.stride(), R=R, NEED_X=need_x, NEED_Y=need_y,
                                             Y_SLOT=2 + need_x, BH=_BH, BW=_BW)
    return s, k


def backward(grad: torch.Tensor, x: torch.Tensor, y: torch.Tensor, maps: torch.Tensor, window: torch.Tensor,
             need_x: bool, need_y: bool) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(dx, dy) from the map's gradient ``grad`` [N, C, h, w] (any strides, an expanded scalar included),
    each laid out as ``torch.empty_like`` its input, None where not needed."""
    N, C, H, W = x.shape
    R = (window.numel() - 1) // 2
    h, w = H - 2 * R, W - 2 * R
    dx = torch.empty_like(x) if need_x else None
    dy = torch.empty_like(y) if need_y else None
    out_x, out_y = dx if need_x else x, dy if need_y else y  # (an output not needed is never written)
    _ssim_backward_kernel[_grid(H, W, N * C)](grad, maps, x, y, window, out_x, out_y, C, H, W, h, w,
                                              N * C * h * w, *grad.stride(), *x.stride(), *y.stride(),
                                              *out_x.stride(), *out_y.stride(), R=R, NEED_X=need_x, NEED_Y=need_y,
                                              Y_SLOT=2 + need_x, BH=_BH, BW=_BW)
    return dx, dy
