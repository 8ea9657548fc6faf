"""Building blocks shared by the decoder, the canvas and the predictor, written for a fast bf16 step.

On CUDA the decoder and predictor keep every activation channels-last (``activation_format``): cuDNN's
bf16 convolutions run in NHWC, so NCHW activations cost a layout conversion before and after every
convolution and its gradients (36 ms of a 287 ms training step on an H100). Elsewhere NCHW, as PyTorch's
CPU kernels prefer. The blocks below work in either layout and compute the same numbers in both.

- ``replicate_pad``: edge replication (each padded pixel copies the nearest border pixel) by copies that
  keep the input's layout, with a backward that sums the padded border into the edge pixels in a few
  slice operations. PyTorch's own ``replication_pad2d_backward`` scatters with atomics and was the
  largest single cost of a training step on an H100 (40 ms of 400 at 256x256, batch 32).
- ``replicate_conv3x3`` / ``ReplicateConv2d``: a 3x3 convolution of the replicate-padded input (the
  predictor's convolutions) without the padded copy: a zero-padded convolution plus the ring's
  difference, whose gradients are added into the convolution's in place. With ``multiple`` > 1 the
  output channels are computed padded to that multiple (zero filters, cut off again) and extra input
  channels of ``x`` (``cat_channels``) meet zero weights: cuDNN's NHWC kernels want channel counts in
  multiples of 8 (and are faster at some larger multiples: ``CUDA_INPUT_MULTIPLE``) and otherwise pad with
  copies of their own. The first extra channel is all ones and carries the bias inside the convolution.
  Same parameters and state_dict keys as ``nn.Conv2d(..., padding=1, padding_mode="replicate")``.
- ``cat_channels``: the channel concatenation of the convolutions' inputs, each source edge-replicated by
  its own padding on the way (the descriptor onto the canvas), with the ones channel and zeros appended; on
  CUDA one Triton pass (``sgmodel.kernels.concat``) instead of a padded copy and PyTorch's per-source copies.
- ``group_norm_gelu`` / ``GroupNorm``: GroupNorm, optionally followed by the exact GELU, in its input's
  dtype (statistics in float32). On CUDA with Triton, for channels-last inputs, one fused kernel pair
  forward and one backward (``sgmodel.kernels.group_norm``): PyTorch's CUDA GroupNorm is NCHW-only and
  converts channels-last tensors both ways. Elsewhere PyTorch's ``F.group_norm`` and ``F.gelu``, which are
  the reference the kernels are tested against. Same parameters and state_dict keys as ``nn.GroupNorm``.
  ``group_norm_gelu_parts`` gives the output as channel blocks for consumers that each read one.
- ``upsample_bilinear``: PyTorch's bilinear resize written in its consumer's dtype; an exact 2x of a
  channels-last CUDA tensor runs Triton kernels (``sgmodel.kernels.upsample``).
- ``compute_dtype``: the dtype convolutions run in here (autocast's, else float32), so that inputs are
  cast once before they are concatenated instead of concatenated in float32 and cast by every consumer.

On the CPU (no autocast) every block computes exactly what its PyTorch counterpart computes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sgmodel.kernels import CAT_KERNEL_SOURCES, channels_last_kernels_run, triton_installed

#: on CUDA, channel counts of concatenated inputs are padded to a multiple of ``CUDA_INPUT_MULTIPLE`` and
#: convolution outputs to one of ``CUDA_OUTPUT_MULTIPLE``: the multiples whose cuDNN NHWC kernels were fastest
#: (`scripts/profile/gpu_conv_channels.py`, H100, bf16, batch 32 at the canvas size, forward + backward: the
#: stacked branches' 259 -> 384 convolution 31.1 ms with 264 input channels, 27.8 with 288, 28.5 with 320; a
#: 37-channel final conv 2.66 ms computing 40 outputs, 2.27 with 48; 36.6 ms unpadded, 259 channels, earlier).
CUDA_INPUT_MULTIPLE = 32
CUDA_OUTPUT_MULTIPLE = 16


def amp_autocast(x: torch.Tensor, amp: bool = True) -> torch.autocast:
    """bf16 autocast when ``amp`` asks for it and ``x`` lives on CUDA (training's and inference's mixed
    precision: the convolutions in bf16; the composer, rasteriser and losses keep float32), else a no-op."""
    return torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp and x.is_cuda)


def activation_format(x: torch.Tensor) -> torch.memory_format:
    """The layout of the decoder's and predictor's activations on ``x``'s device: channels-last on CUDA,
    NCHW elsewhere (module docstring)."""
    return torch.channels_last if x.is_cuda else torch.contiguous_format


def input_multiple(x: torch.Tensor) -> int:
    """Concatenated inputs' channel counts are padded to this multiple on ``x``'s device (1: none)."""
    return CUDA_INPUT_MULTIPLE if x.is_cuda else 1


def output_multiple(x: torch.Tensor) -> int:
    """Convolutions compute their output channels padded to this multiple on ``x``'s device (1: none)."""
    return CUDA_OUTPUT_MULTIPLE if x.is_cuda else 1


def round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


def cat_channels(tensors: list[torch.Tensor], multiple: int = 1, pads: list[int] | None = None,
                 biases: list[torch.Tensor | None] | None = None) -> torch.Tensor:
    """Concatenate [B, C_i, H_i, W_i] tensors of one dtype along channels, each first edge-replicated by
    ``pads[i]`` pixels (``replicate_pad``; default none) to one height and width and given ``biases[i]`` [C_i]
    where there is one (a convolution's bias left to this pass: ``GaussianPredictor``), in the first one's layout
    (``activation_format``), with channels appended up to a multiple of ``multiple``: the first of them all
    ones (the bias channel of ``replicate_conv3x3``), the rest zeros. On CUDA with Triton (at most three
    tensors) one pass writes it all, padding and biases included (``sgmodel.kernels.concat``: the bias added in
    float32, float64 for float64 tensors), with no padded copy of its own; elsewhere the bias is added in the
    tensor's dtype, then the padding and ``torch.cat``: the same values but for that rounding."""
    pads = [0] * len(tensors) if pads is None else list(pads)
    biases = [None] * len(tensors) if biases is None else list(biases)
    x = tensors[0]
    sizes = {(t.shape[0], t.shape[2] + 2 * p, t.shape[3] + 2 * p) for t, p in zip(tensors, pads)}
    if len(pads) != len(tensors) or min(pads) < 0 or len(sizes) != 1 or len({t.dtype for t in tensors}) != 1:
        raise ValueError("cat_channels: tensors must be [B, C, H, W] of one dtype, one batch and, once padded, "
                         f"one size; got {[tuple(t.shape) for t in tensors]}, {[t.dtype for t in tensors]}, "
                         f"pads {pads}")
    if len(biases) != len(tensors) or any(b is not None and b.shape != (t.shape[1],) for t, b in zip(tensors, biases)):
        got = [None if b is None else tuple(b.shape) for b in biases]
        raise ValueError(f"cat_channels: a bias per tensor, [C] or None; got {got} for "
                         f"{[tuple(t.shape) for t in tensors]}")
    total = sum(t.shape[1] for t in tensors)
    width = round_up(total, multiple)
    if x.is_cuda and len(tensors) <= CAT_KERNEL_SOURCES and triton_installed() and x.dtype.is_floating_point:
        return _CatChannels.apply(width, tuple(pads), len(tensors), *tensors, *biases)
    tensors = [replicate_pad(t if b is None else t + b.to(t.dtype).view(1, -1, 1, 1), p)
               for t, p, b in zip(tensors, pads, biases)]
    if width > total:
        spare = x.new_zeros(x.shape[0], width - total, *tensors[0].shape[2:])
        spare[:, 0] = 1.0
        tensors = [*tensors, spare]
    return torch.cat([t.contiguous(memory_format=activation_format(x)) for t in tensors], dim=1)


class _CatChannels(torch.autograd.Function):
    """The Triton kernels of ``sgmodel.kernels.concat`` (CUDA tensors of one dtype, at most three, each with its
    bias or None)."""

    @staticmethod
    def forward(ctx, width: int, pads: tuple[int, ...], n: int, *tensors_and_biases: torch.Tensor | None
                ) -> torch.Tensor:
        from sgmodel.kernels import concat as concat_kernels

        tensors, biases = tensors_and_biases[:n], tensors_and_biases[n:]
        ctx.pads, ctx.shapes, ctx.dtypes = pads, [t.shape for t in tensors], [t.dtype for t in tensors]
        ctx.bias_dtypes = [None if b is None else b.dtype for b in biases]
        return concat_kernels.forward(list(tensors), list(pads), width, list(biases))

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        from sgmodel.kernels import concat as concat_kernels

        n = len(ctx.shapes)
        grads, bias_grads, lo = [], [], 0
        needs = ctx.needs_input_grad[3:]
        for k, (shape, dtype, p, bias_dtype) in enumerate(zip(ctx.shapes, ctx.dtypes, ctx.pads, ctx.bias_dtypes)):
            need_x, need_b = needs[k], bias_dtype is not None and needs[n + k]
            dx = db = None
            if need_x or need_b:
                dx, db = concat_kernels.backward(grad, lo, shape[1], p, shape[2], shape[3], dtype,
                                                 bias_dtype if need_b else None)
            grads.append(dx if need_x else None)
            bias_grads.append(db)
            lo += shape[1]
        return None, None, None, *grads, *bias_grads


class _ReplicatePad(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, p: int) -> torch.Tensor:
        ctx.p = p
        *lead, H, W = x.shape
        fmt = torch.channels_last if x.dim() == 4 and not x.is_contiguous() and x.is_contiguous(
            memory_format=torch.channels_last) else torch.contiguous_format
        out = torch.empty(*lead, H + 2 * p, W + 2 * p, dtype=x.dtype, device=x.device, memory_format=fmt)
        out[..., p:-p, p:-p] = x
        out[..., :p, p:-p] = x[..., :1, :]  # rows first, then whole columns: the corners copy the rows
        out[..., -p:, p:-p] = x[..., -1:, :]
        out[..., :, :p] = out[..., :, p:p + 1]
        out[..., :, -p:] = out[..., :, -p - 1:-p]
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        p = ctx.p
        g = grad[..., p:-p, p:-p].clone()
        # edges (without corners): the padded rows/columns sum into the border row/column
        g[..., 0, :] += grad[..., :p, p:-p].sum(-2)
        g[..., -1, :] += grad[..., -p:, p:-p].sum(-2)
        g[..., :, 0] += grad[..., p:-p, :p].sum(-1)
        g[..., :, -1] += grad[..., p:-p, -p:].sum(-1)
        # corners: each p x p padded corner block sums into the corner pixel
        g[..., 0, 0] += grad[..., :p, :p].sum((-2, -1))
        g[..., 0, -1] += grad[..., :p, -p:].sum((-2, -1))
        g[..., -1, 0] += grad[..., -p:, :p].sum((-2, -1))
        g[..., -1, -1] += grad[..., -p:, -p:].sum((-2, -1))
        return g, None


def replicate_pad(x: torch.Tensor, p: int) -> torch.Tensor:
    """[B, C, H, W] (or [C, H, W]) -> [..., H + 2p, W + 2p] by edge replication; ``p = 0`` returns ``x``."""
    if p < 0:
        raise ValueError(f"padding must be >= 0, got {p}")
    return _ReplicatePad.apply(x, p) if p else x


def _ring_terms(top_row: torch.Tensor, bottom_row: torch.Tensor, left_col: torch.Tensor, right_col: torch.Tensor,
                weight: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """What edge replication adds to a zero-padded 3x3 convolution, per border of the output: the top
    row (``x[:, :, 0]`` replicated in width) meets the kernel's first row, the bottom row its last; the
    left and right columns (zero-padded in height, so that each corner is counted once, by its row) meet
    the kernel's first and last columns. Rows [B,Cin,W] -> [B,Cout,W]; columns [B,Cin,H] -> [B,Cout,H]."""
    return (F.conv1d(F.pad(top_row, (1, 1), mode="replicate"), weight[:, :, 0, :]),
            F.conv1d(F.pad(bottom_row, (1, 1), mode="replicate"), weight[:, :, 2, :]),
            F.conv1d(left_col, weight[:, :, :, 0], padding=1),
            F.conv1d(right_col, weight[:, :, :, 2], padding=1))


def _ring_inputs(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
    return x[:, :, 0, :], x[:, :, -1, :], x[:, :, :, 0], x[:, :, :, -1]


class _ReplicateConv3x3(torch.autograd.Function):
    """Zero-padded convolution plus the ring's difference, with a backward that adds the ring's small
    gradients into the convolution's own gradients in place. Left to autograd, each of the four border
    slices of ``x`` would cost a zero-filled gradient of ``x``'s full size and its addition (about 25 ms
    of a 330 ms training step at the predictor's sizes). The filters are zero-padded to ``x``'s channels
    and to a multiple of ``multiple`` outputs, and the output cut back to the weight's (the gradient of
    the cut is written here, in the activations' layout, not left to autograd's NCHW zero fill). When
    ``x`` has channels beyond the weight's, the first of them is all ones (``cat_channels``) and the bias
    rides on it as the centre tap of the filters: the convolution adds it while it accumulates, and its
    gradient is that tap's weight gradient, instead of an addition over the whole output and a reduction
    of its gradient (5.5 ms of a 192 ms training step on an H100). Inputs share one dtype; autocast is off
    inside."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, multiple: int) -> torch.Tensor:
        cout, cin = weight.shape[:2]
        padded = round_up(cout, multiple)
        ride = bias is not None and x.shape[1] > cin  # the bias rides on x's ones channel ``cin``
        if padded != cout or x.shape[1] != cin:
            w = weight.new_zeros(padded, x.shape[1], 3, 3)
            w[:cout, :cin] = weight
            if ride:
                w[:cout, cin, 1, 1] = bias
            elif bias is not None:
                bias = torch.cat([bias, bias.new_zeros(padded - cout)])
            weight = w
        x = x.contiguous(memory_format=activation_format(x))  # a channel slice: copied once, not per use
        ctx.save_for_backward(x, weight)
        ctx.has_bias, ctx.ride, ctx.cout, ctx.cin = bias is not None and not ride, ride, cout, cin
        with torch.autocast(x.device.type, enabled=False):
            out = F.conv2d(x, weight, None if ride else bias, padding=1)
            top, bottom, left, right = _ring_terms(*_ring_inputs(x), weight)
            out[:, :, 0, :] += top
            out[:, :, -1, :] += bottom
            out[:, :, :, 0] += left
            out[:, :, :, -1] += right
        return out[:, :cout] if padded != cout else out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight = ctx.saved_tensors
        need_x, need_w, need_b, _ = ctx.needs_input_grad
        fmt = activation_format(x)
        if weight.shape[0] != ctx.cout:
            g = grad.new_zeros(grad.shape[0], weight.shape[0], *grad.shape[2:]).contiguous(memory_format=fmt)
            g[:, :ctx.cout] = grad
            grad = g
        else:
            grad = grad.contiguous(memory_format=fmt)
        with torch.autocast(grad.device.type, enabled=False):
            gx, gw, gb = torch.ops.aten.convolution_backward(
                grad, x, weight, [weight.shape[0]] if ctx.has_bias else None, [1, 1], [1, 1], [1, 1], False,
                [0, 0], 1, [need_x, need_w or (need_b and ctx.ride), need_b and ctx.has_bias])
            if need_x or need_w:
                with torch.enable_grad():
                    ring = [t.detach().requires_grad_(need_x) for t in _ring_inputs(x)]
                    w = weight.detach().requires_grad_(need_w)
                    wrt = (ring if need_x else []) + ([w] if need_w else [])
                    grads = torch.autograd.grad(_ring_terms(*ring, w), wrt, _ring_inputs(grad))
                if need_x:
                    for view, g in zip(_ring_inputs(gx), grads[:4]):
                        view += g  # in place: the corners get their row's and their column's share
                if need_w:
                    gw += grads[-1]  # the ring's terms use no centre tap: the bias channel's stays as it is
        if ctx.ride and need_b:
            gb = gw[:ctx.cout, ctx.cin, 1, 1].clone()
        gw = gw[:ctx.cout, :ctx.cin] if need_w else None
        gb = None if gb is None else gb[:ctx.cout]
        return gx, gw, gb, None


def replicate_conv3x3(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, multiple: int = 1
                      ) -> torch.Tensor:
    """3x3 convolution of ``x`` [B,Cin',H,W] padded by one pixel of edge replication -> [B,Cout,H,W].

    Computed as cuDNN's zero-padded convolution (which pads inside the kernel, without a padded copy of
    the input) plus the difference replication makes, which lives on the one-pixel ring only
    (``_ring_terms``). ``x`` may carry channels beyond the weight's Cin (``cat_channels``): the first all
    ones, which carries the bias, the rest zeros, meeting zero filters; ``multiple``: compute Cout rounded
    up to it (module docstring). Under autocast it runs in autocast's dtype, as ``F.conv2d`` would; else
    in ``x``'s."""
    if x.shape[1] < weight.shape[1]:
        raise ValueError(f"replicate_conv3x3: input has {x.shape[1]} channels, the weight wants {weight.shape[1]}")
    dtype = torch.get_autocast_dtype(x.device.type) if torch.is_autocast_enabled(x.device.type) else x.dtype
    return _ReplicateConv3x3.apply(x.to(dtype), weight.to(dtype), None if bias is None else bias.to(dtype), multiple)


class ReplicateConv2d(nn.Conv2d):
    """3x3 convolution of the input padded by edge replication to keep its size (``replicate_conv3x3``,
    output channels padded to ``output_multiple`` inside)."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(cin, cout, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return replicate_conv3x3(x, self.weight, self.bias, output_multiple(x))


def compute_dtype(device: torch.device) -> torch.dtype:
    """The dtype convolutions run in on ``device`` now: autocast's when it is on, else float32."""
    if torch.is_autocast_enabled(device.type):
        return torch.get_autocast_dtype(device.type)
    return torch.float32


def group_norm(x: torch.Tensor, groups: int, weight: torch.Tensor, bias: torch.Tensor, eps: float) -> torch.Tensor:
    """``F.group_norm`` in ``x``'s dtype (statistics accumulate in float32 on CUDA for bf16/fp16)."""
    with torch.autocast(x.device.type, enabled=False):
        return F.group_norm(x, groups, weight.to(x.dtype), bias.to(x.dtype), eps)


class _GroupNormGELU(torch.autograd.Function):
    """The Triton kernels of ``sgmodel.kernels.group_norm`` for a channels-last CUDA tensor; the output as
    ``parts`` channel blocks (a tuple of tensors)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, groups: int, eps: float,
                gelu: bool, parts: int) -> tuple[torch.Tensor, ...]:
        from sgmodel.kernels import group_norm as group_norm_kernels

        ys, mean, rstd = group_norm_kernels.forward(x, groups, weight, bias, eps, gelu, parts)
        ctx.save_for_backward(x, weight, bias, mean, rstd)
        ctx.groups, ctx.gelu = groups, gelu
        return tuple(ys)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor):
        from sgmodel.kernels import group_norm as group_norm_kernels

        x, weight, bias, mean, rstd = ctx.saved_tensors
        dx, dw, db = group_norm_kernels.backward(list(grads), x, mean, rstd, ctx.groups, weight, bias, ctx.gelu,
                                                 ctx.needs_input_grad[0])
        return dx, dw, db, None, None, None, None


def compiles(device: torch.device, wanted: bool = True) -> bool:
    """Whether training runs a block through ``torch.compile`` (the LPIPS term's VGG16): wanted (not
    ``--no-compile-lpips``), on CUDA, with Triton installed (inductor writes its GPU code in Triton)."""
    return wanted and device.type == "cuda" and triton_installed()


def group_norm_gelu(x: torch.Tensor, groups: int, weight: torch.Tensor, bias: torch.Tensor, eps: float,
                    gelu: bool = True) -> torch.Tensor:
    """GroupNorm of ``x`` [B,C,H,W] (``groups`` contiguous channel blocks, per-channel affine ``weight``,
    ``bias``), then the exact GELU when ``gelu``; in ``x``'s dtype and layout, autocast or not. Fused
    Triton kernels where ``channels_last_kernels_run``, else ``F.group_norm`` and ``F.gelu``."""
    return group_norm_gelu_parts(x, groups, weight, bias, eps, gelu, parts=1)[0]


def group_norm_gelu_parts(x: torch.Tensor, groups: int, weight: torch.Tensor, bias: torch.Tensor, eps: float,
                          gelu: bool = True, parts: int = 1) -> list[torch.Tensor]:
    """``group_norm_gelu`` of ``x`` as ``parts`` equal channel blocks [B, C / parts, H, W] (each whole
    groups; at most 3), for consumers that each read one block. Where the Triton kernels run, each block
    is its own channels-last tensor (written so, and its gradient read so: no copy of a channel slice,
    no concatenation of gradients); elsewhere views of one output."""
    if channels_last_kernels_run(x):
        with torch.autocast(x.device.type, enabled=False):
            return list(_GroupNormGELU.apply(x, weight, bias, groups, eps, gelu, parts))
    y = group_norm(x, groups, weight, bias, eps)
    return list((F.gelu(y) if gelu else y).split(x.shape[1] // parts, dim=1))


class GroupNorm(nn.GroupNorm):
    """``nn.GroupNorm`` that runs in its input's dtype and layout (``group_norm_gelu`` without the GELU;
    ``gelu_after`` applies it with one)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return group_norm_gelu(x, self.num_groups, self.weight, self.bias, self.eps, gelu=False)

    def gelu_after(self, x: torch.Tensor) -> torch.Tensor:
        """GELU(GroupNorm(x)), fused on CUDA."""
        return group_norm_gelu(x, self.num_groups, self.weight, self.bias, self.eps, gelu=True)


class _BiasGELU(torch.autograd.Function):
    """The Triton kernels of ``sgmodel.kernels.bias_gelu`` (a channels-last CUDA tensor)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        from sgmodel.kernels import bias_gelu as bias_gelu_kernels

        ctx.save_for_backward(x, bias)
        return bias_gelu_kernels.forward(x, bias)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        from sgmodel.kernels import bias_gelu as bias_gelu_kernels

        x, bias = ctx.saved_tensors
        dx, db = bias_gelu_kernels.backward(grad, x, bias)
        return dx, db.to(bias.dtype)


def bias_gelu(x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """GELU(x + bias) (exact GELU) of x [B, C, H, W], bias [C], in x's dtype: fused Triton kernels for a
    channels-last CUDA tensor (``sgmodel.kernels.bias_gelu``: x + bias in float32, its gradient in the same
    pass as x's), else PyTorch's addition (the bias cast to x's dtype, as a convolution under autocast adds
    it) and GELU."""
    if channels_last_kernels_run(x):
        return _BiasGELU.apply(x, bias)
    return F.gelu(x + bias.to(x.dtype).view(-1, 1, 1))


def conv_gelu(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """GELU(conv(x)) with the convolution's bias added by ``bias_gelu``, not by the convolution."""
    return bias_gelu(F.conv2d(x, conv.weight, None, conv.stride, conv.padding, conv.dilation, conv.groups),
                     conv.bias)


class _Upsample2x(torch.autograd.Function):
    """The Triton kernels of ``sgmodel.kernels.upsample`` (a channels-last CUDA tensor resized to 2x)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        from sgmodel.kernels import upsample as upsample_kernels

        ctx.size, ctx.dtype = tuple(x.shape[-2:]), x.dtype
        return upsample_kernels.forward(x, dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        from sgmodel.kernels import upsample as upsample_kernels

        return upsample_kernels.backward(grad, *ctx.size, ctx.dtype), None


def upsample_bilinear(x: torch.Tensor, size: tuple[int, int], dtype: torch.dtype) -> torch.Tensor:
    """Bilinear resize of ``x`` [B,C,h,w] to ``size`` as ``F.interpolate(..., align_corners=False)``, computed
    in float32 and returned in ``dtype`` (its consumer's: a resize that feeds a bf16 convolution writes
    bf16, not float32 and then a cast). Triton kernels for an exact 2x of a channels-last CUDA tensor
    (``sgmodel.kernels.upsample``: the decoder's last upsampling, 6 ms less a training step on an H100),
    else ``F.interpolate`` (float32 under autocast) and a cast."""
    h, w = x.shape[-2:]
    if tuple(size) == (2 * h, 2 * w) and channels_last_kernels_run(x):
        with torch.autocast(x.device.type, enabled=False):
            return _Upsample2x.apply(x, dtype)
    return F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=False).to(dtype)
