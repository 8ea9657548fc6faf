"""Parameters of the StereoGaussians model and its training, as nested dataclasses.

Every default is the paper's value (section 4, appendix A; SPEC section 7); a comment per field gives
its unit and where it comes from. ``ModelParams`` travels inside every checkpoint (``to_dict`` /
``from_dict``), so a checkpoint rebuilds its own model. ``PRESETS`` holds small configurations for
machines without a GPU: they change sizes and schedules, never the method.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

EDGE_MASKS = ("none", "hard", "soft")
MAX_SEED = 2**63 - 1  # seeds numpy and torch both take (torch.manual_seed refuses more than 64 bits)


class ConfigurationError(ValueError):
    """A combination of settings that cannot be built (the message names the settings)."""


@dataclass
class EncoderParams:
    name: str = "psmnet-kitti"  # registry name, see `sgmodel.encoders.available_encoders()`
    weights: str | None = None  # local weights file; None: the cache of `sgmodel weights fetch NAME`
    repo: str | None = None  # the user's checkout of the encoder's code (foundation-stereo variants only)


@dataclass
class DecoderParams:
    channels: int = 128  # DPT descriptor width C of Phi (appendix A "Dense predictor")
    groups: int = 8  # GroupNorm groups after each 1x1 projection
    rgbd_scales: tuple[int, ...] = (2, 4, 8)  # decoder scales for an encoder without features (sgbm)


@dataclass
class PredictorParams:
    channels: int = 128  # width of the regressor output h and of each branch's hidden layer (appendix A)
    groups: int = 8  # GroupNorm groups inside each branch
    init_std: float = 1e-3  # std of the final-conv weights of opacity, offset and quaternion channels
    # ("start small and non-zero"); scale, SH and the whole dz branch start at exactly zero


@dataclass
class ComposerParams:
    back_layer: bool = True  # two Gaussian layers; False: front layer only (Table 4 "without back layer")
    edge_mask: str = "none"  # back-layer opacity gate: "none" (default), "hard" or "soft" (appendix A)
    composer: bool = True  # residual attribute composition; False: plain activations (Table 4,
    # "without composer"; exact meaning in sgmodel.model.composer)


@dataclass
class ModelParams:
    encoder: EncoderParams = field(default_factory=EncoderParams)
    decoder: DecoderParams = field(default_factory=DecoderParams)
    predictor: PredictorParams = field(default_factory=PredictorParams)
    composer: ComposerParams = field(default_factory=ComposerParams)
    resolution: int = 256  # S: square training and inference size, pixels (section 5)
    padding: int = 16  # P: canvas padding per side, pixels at S = 256 (section 4.3, Table 4 block D)
    descriptor: bool = True  # feed the DPT descriptor Phi to the predictor (Table 4 "without descriptor")
    rgbd: bool = True  # RGB and depth in the decoder and predictor inputs (Table 4 "without RGB-D")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelParams:
        d = dict(d)
        dec = dict(d.pop("decoder", {}))
        if "rgbd_scales" in dec:
            dec["rgbd_scales"] = tuple(dec["rgbd_scales"])
        return cls(encoder=EncoderParams(**d.pop("encoder", {})), decoder=DecoderParams(**dec),
                   predictor=PredictorParams(**d.pop("predictor", {})),
                   composer=ComposerParams(**d.pop("composer", {})), **d)

    def validate(self) -> None:
        """Raise ConfigurationError naming the flag (the field of the same name) for a configuration that
        cannot be built."""
        if self.resolution < 16 or self.resolution % 16:
            raise ConfigurationError(f"--resolution {self.resolution}: must be a multiple of 16 and >= 16")
        if self.padding < 0:
            raise ConfigurationError(f"--padding {self.padding}: must be >= 0")
        if self.composer.edge_mask not in EDGE_MASKS:
            raise ConfigurationError(f"--edge-mask {self.composer.edge_mask!r}: must be one of {EDGE_MASKS}")
        if self.composer.edge_mask != "none" and not self.composer.back_layer:
            raise ConfigurationError(f"--edge-mask {self.composer.edge_mask}: an edge mask gates the back layer; it "
                                     "cannot be combined with --no-back-layer")
        for name, width, groups in (("decoder", self.decoder.channels, self.decoder.groups),
                                    ("predictor", self.predictor.channels, self.predictor.groups)):
            if width < 1 or groups < 1 or width % groups:
                raise ConfigurationError(f"--{name}-channels {width}: must be a positive multiple of {name}.groups "
                                         f"({groups})")


@dataclass
class TrainParams:
    steps: int = 30_000  # optimiser steps (appendix A "Training and model selection")
    batch_size: int = 32  # stereo pairs per step, over all ranks (appendix A)
    accumulate: int = 1  # shares each rank's batch is computed in, one after another, gradients averaged
    targets: int = 4  # target views per pair drawn from the stored ten (SPEC section 7)
    lr: float = 4e-4  # AdamW peak learning rate (appendix A "Optimisation")
    weight_decay: float = 0.01  # AdamW (appendix A)
    betas: tuple[float, float] = (0.9, 0.999)  # AdamW (appendix A)
    warmup: float = 0.09  # OneCycleLR pct_start: 2,700 of 30,000 steps (appendix A)
    div_factor: float = 25.0  # OneCycleLR initial lr = lr / div_factor (appendix A)
    final_div_factor: float = 100.0  # OneCycleLR final lr = initial lr / final_div_factor (appendix A)
    lpips_weight: float = 0.05  # L = MSE + 0.05 LPIPS-VGG (appendix A "Rendering objective")
    val_every: int = 3_000  # steps between validations; the best validation PSNR is the model
    val_samples: int | None = None  # cap on validation samples (None: the whole split)
    log_every: int = 10  # steps between metrics.jsonl records
    seed: int = 0  # data order, target draws and initialisation
    workers: int | None = None  # DataLoader worker processes per rank (None: ``loader_workers``' share of the host)
    amp: bool = True  # bf16 autocast for the encoder and the convolutions on CUDA (rasteriser float32)
    compile_lpips: bool = True  # torch.compile the LPIPS term's VGG16 trunk on CUDA (~15 s once per process)
    sheet_samples: int = 4  # validation samples shown in each contact sheet
    ddp_bucket_mb: float = 25.0  # DDP gradient bucket size (MiB) on several GPUs (PyTorch's default)
    ddp_bf16_grads: bool = False  # all-reduce the gradients in bfloat16 on several GPUs (DDP comm hook)
    profile: bool = False  # per-rank time of each step's phases in metrics.jsonl (``sgmodel.train.step_profile``)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def validate(self) -> None:
        """ValueError naming the flag (the field of the same name) for a schedule that cannot run."""
        for name in ("steps", "batch_size", "accumulate", "targets", "val_every", "log_every", "sheet_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)}: must be >= 1")
        if self.val_samples is not None and self.val_samples < 1:
            raise ValueError(f"--val-samples {self.val_samples}: must be >= 1")
        for name, low in (("lr", 0.0), ("weight_decay", None), ("lpips_weight", None), ("div_factor", 0.0),
                          ("final_div_factor", 0.0)):
            value = getattr(self, name)
            if not math.isfinite(value) or (value <= low if low is not None else value < 0):
                raise ValueError(f"--{name.replace('_', '-')} {value}: must be a finite number "
                                 f"{'> 0' if low is not None else '>= 0'}")
        if not 0 < self.warmup < 1:
            raise ValueError(f"--warmup {self.warmup}: must be in (0, 1)")
        if not all(0 <= b < 1 for b in self.betas):
            raise ValueError(f"betas {self.betas}: each must be in [0, 1)")
        if not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"--seed {self.seed}: must be in 0..{MAX_SEED}")
        if self.workers is not None and self.workers < 0:
            raise ValueError(f"--workers {self.workers}: must be >= 0")
        if not (math.isfinite(self.ddp_bucket_mb) and self.ddp_bucket_mb > 0):
            raise ValueError(f"--ddp-bucket-mb {self.ddp_bucket_mb}: must be a finite number > 0")


# Small configurations for a CPU: the same method at a size two cores train in minutes.
PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "paper": {"model": {}, "train": {}},
    "cpu-small": {
        "model": {"resolution": 64, "padding": 4, "encoder": {"name": "sgbm"},
                  "decoder": {"channels": 32}, "predictor": {"channels": 32}},
        "train": {"steps": 200, "batch_size": 4, "targets": 2, "val_every": 50, "log_every": 10, "workers": 0},
    },
}
