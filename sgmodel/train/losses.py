"""The training objective (paper section 4; SPEC section 7 "Objective").

``MSE(target, render) + 0.05 * LPIPS-VGG(target, render)`` over the full target images (no masks, the
input views are not supervised). LPIPS needs torchvision's ImageNet VGG16 weights, which cannot be
downloaded here; without them the objective is ``MSE + 0.05 * (1 - SSIM)`` (skimage-style SSIM,
``sgmodel.metrics.image.ssim_map``) and says so in ``Objective.description`` (for the first log lines and
``config.json``). Renders are not clipped: gradients must reach colours that leave [0, 1]. In training on
CUDA the LPIPS network runs under bf16 autocast like the model's convolutions (VGG16 on 2 x 128 images of
256x256 per step is otherwise the largest cost of a step); the MSE and the SSIM term stay float32.
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from sgmodel.metrics.image import ssim_map
from sgmodel.metrics.lpips import LPIPS, create_lpips, vgg16_missing_message
from sgmodel.model.layers import amp_autocast

#: weight of the perceptual term (paper section 4, "Training objective").
PERCEPTUAL_WEIGHT = 0.05


class Objective:
    """``loss(render, target)`` for images [..., 3, H, W] in [0, 1]; returns (scalar loss, parts).

    ``name`` is "mse+lpips-vgg" or "mse+ssim"; ``description`` is a one-line human account of it."""

    def __init__(self, lpips_net: LPIPS | None, reason: str = "", weight: float = PERCEPTUAL_WEIGHT,
                 amp: bool = False):
        self.lpips_net = lpips_net
        self.weight = weight
        self.amp = amp
        if lpips_net is not None:
            self.name = "mse+lpips-vgg"
            self.description = (f"MSE + {weight} * LPIPS-VGG (v0.1, VGG16 sha256 {lpips_net.vgg_sha256}"
                                f"{', bf16 autocast on CUDA' if amp else ''})")
        else:
            self.name = "mse+ssim"
            self.description = f"MSE + {weight} * (1 - SSIM) instead of LPIPS-VGG: {reason}"

    def to_config(self) -> dict:
        """What ``config.json`` records about the loss."""
        return {"name": self.name, "description": self.description, "perceptual_weight": self.weight,
                "vgg16_sha256": None if self.lpips_net is None else self.lpips_net.vgg_sha256}

    def __call__(self, render: Tensor, target: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Scalar loss and its detached parts (``mse`` and ``lpips`` or ``ssim``, means over images)."""
        if render.shape != target.shape:
            raise ValueError(f"loss: render {tuple(render.shape)} and target {tuple(target.shape)} differ")
        mse = (render - target).pow(2).mean()
        if self.lpips_net is not None:
            with amp_autocast(render, self.amp):
                perceptual = self.lpips_net(target, render).float().mean()
            parts = {"mse": mse.detach(), "lpips": perceptual.detach()}
        else:
            s = ssim_map(target, render, border=False).mean()
            perceptual = 1 - s
            parts = {"mse": mse.detach(), "ssim": s.detach()}
        return mse + self.weight * perceptual, parts


def create_objective(vgg_path: str | os.PathLike | None = None, lin_path: str | os.PathLike | None = None,
                     device: str | torch.device = "cpu", weight: float = PERCEPTUAL_WEIGHT,
                     amp: bool = False, compile_trunk: bool = False) -> Objective:
    """The objective on ``device``: LPIPS-VGG when VGG16 weights are found (``vgg_path`` or torch's hub
    cache), else the SSIM fallback. Weights that are given but unusable raise ``WeightsError``. ``amp``:
    the LPIPS network's convolutions in bf16 on CUDA (training; the metrics of ``eval`` stay float32).
    ``compile_trunk``: its VGG16 through ``torch.compile`` (``LPIPS.compile_trunk``; for CUDA)."""
    net = create_lpips(vgg_path, lin_path, device)
    if net is not None and compile_trunk:
        net.compile_trunk()
    return Objective(net, reason="" if net is not None else vgg16_missing_message(), weight=weight, amp=amp)
