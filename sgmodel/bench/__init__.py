"""Model benchmarks (``sgmodel bench ...``), each a module with ``add_arguments(parser)`` and ``run(args)``
that prints a markdown table: ``train`` (one training step split by stage, peak memory), ``encoders``
(each encoder's time per pair and disparity error against rendered depth) and ``predict`` (one pair to a
scene in a warm process, split by stage; ``--video`` in ``predict_video``). Their shared pieces are here."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

import torch

from scenesplat_stereo.common.ownership import OwnedFile

if TYPE_CHECKING:
    from sgmodel.model.network import Predictor


def report(text: str, out: OwnedFile) -> None:
    """Print a benchmark's markdown and, with ``--out``, write it there too: ``out`` is made by the benchmark
    before any work (``OwnedFile(args.out, "--out", OWNER)``: a file it did not write is refused at once, its own
    earlier report replaced) and writes atomically, with its manifest."""
    print(text)
    out.write(text)


def synthetic_pair(width: int, height: int, device: torch.device, shift: int = 0) -> tuple[torch.Tensor, ...]:
    """(left, right [1,3,H,W] in [0,1], K [1,3,3], baseline [1] metres): smooth texture, 4 px disparity;
    ``shift`` moves the texture that many pixels to the left (a camera panning, for video frames)."""
    g = torch.Generator().manual_seed(0)
    low = torch.rand(1, 3, max(2, height // 16), max(2, (width + shift) // 16 + 1), generator=g)
    wide = torch.nn.functional.interpolate(low, size=(height, width + shift + 4), mode="bicubic",
                                           align_corners=False).clamp(0, 1)
    left = wide[..., shift:shift + width]
    right = wide[..., shift + 4:shift + 4 + width]
    f = 0.9 * max(width, height)
    K = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]])
    return left.to(device), right.to(device), K.to(device), torch.tensor([0.1], device=device)


def describe(args: argparse.Namespace, predictor: Predictor, device: torch.device) -> str:
    """'<device> (<checkpoint or fresh model>, encoder <name>, <bf16 autocast or float32>)' for a report."""
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    model = f"checkpoint {args.checkpoint}" if args.checkpoint else "fresh model"
    dtype = "bf16 autocast" if predictor.amp and device.type == "cuda" else "float32"
    return f"{name} ({model}, encoder {predictor.model.params.encoder.name}, {dtype})"
