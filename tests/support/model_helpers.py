"""Small stand-ins for the model tests: an encoder with features at two scales and a synthetic batch."""

from __future__ import annotations

import torch

from sgmodel.encoders import EncoderOutput, StereoEncoder


class StandInEncoder(StereoEncoder):
    """Frozen, deterministic: disparity from a fixed plane, features = fixed random projections of the
    left image at scales 2 and 4 (so the decoder sees real feature maps)."""

    name = "stand-in"
    feature_channels = (6, 8)
    feature_scales = (2, 4)
    weights_sha256 = None

    def __init__(self, disparity: float = 8.0) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.proj2 = torch.nn.Conv2d(3, 6, 1)
        self.proj4 = torch.nn.Conv2d(3, 8, 1)
        with torch.no_grad():
            for conv in (self.proj2, self.proj4):
                conv.weight.copy_(torch.randn(conv.weight.shape, generator=g))
                conv.bias.zero_()
        self.disparity = disparity
        self.freeze()

    def encode(self, left: torch.Tensor, right: torch.Tensor) -> EncoderOutput:
        B, _, H, W = left.shape
        d = torch.full((B, 1, H, W), self.disparity, device=left.device)
        f2 = self.proj2(torch.nn.functional.avg_pool2d(left, 2, ceil_mode=True))
        f4 = self.proj4(torch.nn.functional.avg_pool2d(left, 4, ceil_mode=True))
        return EncoderOutput(disparity=d, features=[f2, f4])


def textured_batch(B: int = 2, T: int = 2, S: int = 32, seed: int = 0) -> dict:
    """Pairs of a textured fronto-parallel plane with targets that are the left image itself, seen from
    slightly shifted cameras (the model must learn to reproduce them)."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(B, 3, S // 4, S // 4, generator=g)
    left = torch.nn.functional.interpolate(low, size=(S, S), mode="bilinear", align_corners=False)
    f = S * 1.0
    K = torch.tensor([[f, 0, S / 2], [0, f, S / 2], [0, 0, 1.0]]).expand(B, 3, 3).clone()
    view = torch.eye(4).expand(B, T, 4, 4).clone()
    view[..., 0, 3] = torch.linspace(-0.02, 0.02, T)
    return {"left": left, "right": left.roll(-2, dims=-1), "K": K, "baseline": torch.full((B,), 0.1),
            "targets": left[:, None].expand(B, T, 3, S, S).clone(),
            "masks": torch.ones(B, T, 1, S, S, dtype=torch.bool), "target_viewmats": view,
            "target_Ks": K[:, None].expand(B, T, 3, 3).clone(), "target_ids": torch.arange(T).expand(B, T),
            "keys": [f"s{i}" for i in range(B)], "scenes": ["plane"] * B}


def sgmodel_status(argv) -> int:
    """``sgmodel ARGV``'s exit status, through the command line's one error path (argparse's refusals
    included)."""
    from sgmodel.cli import main

    try:
        return main([str(a) for a in argv])
    except SystemExit as e:
        return e.code


def predict_status(argv) -> int:
    """``sgmodel predict ARGV``'s exit status (``sgmodel_status``)."""
    return sgmodel_status(["predict", *argv])


def record_compile(monkeypatch) -> list:
    """Replace ``torch.compile`` by a recorder: the list returned gets each call's options, then "call" each
    time a compiled function runs (eagerly). For the CPU tests of what is handed to compilation."""
    seen = []

    def recorder(fn, **options):
        seen.append(options)

        def run(*args, **kwargs):
            seen.append("call")
            return fn(*args, **kwargs)
        return run

    monkeypatch.setattr(torch, "compile", recorder)
    return seen


def layers_case() -> tuple:
    """A small float64 model (stand-in encoder, 32x32 input, padding 4, 16 channels, 4 groups) with every
    weight drawn at std 0.2 (no zero-initialised head), and inputs for ``model.layers``:
    (model, left, z, features, K)."""
    from sgmodel.config import ModelParams
    from sgmodel.model.network import StereoGaussians

    torch.manual_seed(0)
    p = ModelParams(resolution=32, padding=4)
    p.decoder.channels = p.predictor.channels = 16
    p.decoder.groups = p.predictor.groups = 4
    model = StereoGaussians(p, StandInEncoder()).double()
    with torch.no_grad():
        for t in model.parameters():
            t.normal_(std=0.2)
    left = torch.rand(2, 3, 32, 32, dtype=torch.float64)
    z = 1 + torch.rand(2, 1, 32, 32, dtype=torch.float64)
    K = torch.tensor([[30.0, 0, 16], [0, 30, 16], [0, 0, 1]], dtype=torch.float64).expand(2, 3, 3)
    return model, left, z, model.encoder(left, left).features, K
