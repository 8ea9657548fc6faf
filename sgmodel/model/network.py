"""StereoGaussians: frozen stereo encoder -> DPT decoder -> canvas -> Gaussian predictor -> composer.

``create_model(params)`` builds the model from ``ModelParams`` (ml-sharp's ``create_predictor`` style);
``load_predictor(checkpoint)`` rebuilds a trained one for ``eval`` and ``predict``. The encoder is frozen
and kept outside the module tree on purpose: it is never in ``parameters()``, ``state_dict()``, the
optimiser, DDP's gradient buckets or a checkpoint (SPEC section 7); ``model.to(device)`` moves it too.

Everything is in the left camera's frame, OpenCV axes, metres; images [B,3,H,W] in [0,1]; K in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from sgmodel.config import ModelParams
from sgmodel.encoders import StereoEncoder
from sgmodel.encoders.flags import build_encoder, merge_encoder
from sgmodel.model import canvas
from sgmodel.model.composer import compose, gaussian_validity
from sgmodel.model.decoder import DPTDecoder
from sgmodel.model.geometry import depth_from_disparity, disparity_validity
from sgmodel.model.layers import amp_autocast
from sgmodel.model.predictor import GaussianPredictor


@dataclass
class Prediction:
    """One forward pass. gaussians: the composer's dict (means [B,N,3], quats [B,N,4] wxyz, scales [B,N,3],
    opacities [B,N], sh [B,N,9,3]); depth z [B,1,H,W] metres and disparity [B,1,H,W] pixels at the input
    size; canvas_K [B,3,3]; front/back [B,37,Hc,Wc] and dz [B,1,Hc,Wc] are the predictor's raw outputs (back
    and dz are None without a back layer); from ``Predictor.predict`` (None in training, which renders all N
    Gaussians) valid [B,N] bool: the Gaussians that stand on a stereo depth (``composer.gaussian_validity``;
    ``sgmodel predict`` drops the others) and pixel_valid [B,1,H,W] bool, the pixels with one
    (``geometry.disparity_validity``)."""

    gaussians: dict[str, torch.Tensor]
    depth: torch.Tensor
    disparity: torch.Tensor
    canvas_K: torch.Tensor
    front: torch.Tensor
    back: torch.Tensor | None
    dz: torch.Tensor | None
    valid: torch.Tensor | None = None
    pixel_valid: torch.Tensor | None = None


def check_inputs(left: torch.Tensor, right: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor) -> None:
    """ValueError naming the input (and the batch items) for anything the model cannot use. The shapes are read
    on the host; K's and the baseline's values on their device, brought back in one transfer: for inputs on a GPU,
    one host synchronisation (training checks its batches on the host before their copy: ``step.device_batch``)."""
    if left.ndim != 4 or left.shape[1] != 3 or left.shape != right.shape:
        raise ValueError(f"left and right must both be [B, 3, H, W]; got {tuple(left.shape)} and {tuple(right.shape)}")
    B, _, H, W = left.shape
    if min(H, W) < 16:
        raise ValueError(f"images of {W}x{H} pixels are too small: both sides must be >= 16")
    if K.shape != (B, 3, 3):
        raise ValueError(f"K must be [B, 3, 3] = [{B}, 3, 3], got {list(K.shape)}")
    if baseline.shape != (B,):
        raise ValueError(f"baseline must be [B] = [{B}], got {list(baseline.shape)}")
    bad_K = (~torch.isfinite(K).flatten(1).all(1) | (K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0)
             | (K[:, 2, 0] != 0) | (K[:, 2, 1] != 0) | (K[:, 2, 2] != 1))
    bad_baseline = ~torch.isfinite(baseline) | (baseline <= 0)
    bad = torch.stack([bad_K, bad_baseline]).tolist()
    if any(bad[0]):
        raise ValueError(f"K must be finite, with positive focal lengths and the last row 0 0 1: not so for batch items "
                         f"{_items(bad[0])}")
    if any(bad[1]):
        raise ValueError(f"baseline must be finite and > 0 metres: not so for batch items {_items(bad[1])} "
                         f"(baseline {baseline.tolist()})")


def _items(flags: list[bool]) -> list[int]:
    return [i for i, flag in enumerate(flags) if flag]


@torch.no_grad()
def encode_pair(encoder: StereoEncoder, left: torch.Tensor, right: torch.Tensor
                ) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The frozen encoder on a pair: disparity [B,1,H,W] float32 and features (as the encoder gives them),
    under bf16 autocast when the caller enabled it on CUDA. ValueError naming the batch items whose disparity
    is not finite. One function for the model and the encoder cache, so both compute the same outputs."""
    enabled = left.is_cuda and torch.is_autocast_enabled("cuda")
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=enabled):
        out = encoder(left, right)
    disparity = out.disparity.float()
    if not torch.isfinite(disparity).all():
        bad = (~torch.isfinite(disparity)).flatten(1).any(1).nonzero().flatten().tolist()
        raise ValueError(f"encoder {encoder.name!r} returned non-finite disparity for batch items {bad}")
    return disparity, [f.detach() for f in out.features]


class StereoGaussians(nn.Module):
    """The trainable decoder and predictor around a frozen encoder (attribute ``encoder``)."""

    def __init__(self, params: ModelParams, encoder: StereoEncoder) -> None:
        super().__init__()
        params.validate()
        self.params = params
        self.__dict__["encoder"] = encoder  # frozen: deliberately not a registered submodule
        use_phi = params.descriptor
        self.decoder = DPTDecoder(encoder.feature_channels, encoder.feature_scales, params.decoder.channels,
                                  params.decoder.groups, params.rgbd, params.decoder.rgbd_scales) if use_phi else None
        self.predictor = GaussianPredictor(params.predictor, params.decoder.channels if use_phi else 0, params.rgbd,
                                           params.composer.back_layer)

    def _apply(self, fn, recurse=True):  # .to()/.cuda()/.float() move the frozen encoder as well
        self.encoder._apply(fn)
        return super()._apply(fn, recurse)

    def encode(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Frozen encoder (``encode_pair``): disparity [B,1,H,W] float32 and features."""
        return encode_pair(self.encoder, left, right)

    def layers(self, left: torch.Tensor, z: torch.Tensor, features: list[torch.Tensor], K: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, canvas.Canvas]:
        """Decoder at the input size, then the canvas, then the predictor: (front, back, dz, canvas)."""
        P = self.params.padding
        phi, phi_bias = self.decoder.without_last_bias(features, left, z) if self.decoder is not None else (None, None)
        c = canvas.Canvas(rgb=canvas.extend(left, P), depth=canvas.extend(z, P), K=canvas.canvas_intrinsics(K, P))
        front, back, dz = self.predictor(c.rgb, c.depth, phi, phi_padding=P, phi_bias=phi_bias)  # phi extended there
        return front, back, dz, c

    def compose(self, front: torch.Tensor, back: torch.Tensor | None, dz: torch.Tensor | None, c: canvas.Canvas,
                baseline: torch.Tensor) -> dict[str, torch.Tensor]:
        """The composer in float32 (the predictor may run in bf16: its branches are read as they are and composed
        in float32), not through ``torch.compile``: on CUDA it computed the back layer's depth wrong at some batch
        shapes (docs/benchmarks.md "Issue 34, fifth lease")."""
        p = self.params.composer
        dz = None if dz is None else dz.float()
        return compose(front, back, dz, c.depth, c.rgb.float(), c.K, baseline, back_layer=p.back_layer,
                       edge_mask=p.edge_mask, composer=p.composer)

    def forward(self, left: torch.Tensor, right: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor,
                doffs: float = 0.0, encoded: tuple[torch.Tensor, list[torch.Tensor]] | None = None,
                inputs_checked: bool = False) -> Prediction:
        """left/right [B,3,H,W] in [0,1], K [B,3,3] pixels, baseline [B] metres -> Prediction. ``doffs``:
        the pair's principal-point disparity offset in pixels (Middlebury), added to the encoder's.
        ``encoded``: the encoder's (disparity [B,1,H,W], features) for this pair, read from an encoder cache
        (``sgmodel.data.encoder_cache``); the encoder does not run. ``inputs_checked``: the caller has passed these
        inputs through ``check_inputs`` (on the host, before copying them: ``step.device_batch``)."""
        if not inputs_checked:
            check_inputs(left, right, K, baseline)
        if encoded is None:
            disparity, features = self.encode(left, right)
        else:
            disparity, features = encoded
            if disparity.shape != (left.shape[0], 1) + left.shape[-2:]:
                raise ValueError(f"encoded disparity has shape {tuple(disparity.shape)}, the pair "
                                 f"{tuple(left.shape)}")
        z = depth_from_disparity(disparity, K[:, 0, 0], baseline, doffs=doffs)
        front, back, dz, c = self.layers(left, z, features, K)
        return Prediction(self.compose(front, back, dz, c, baseline), z, disparity, c.K, front, back, dz)

    def validity(self, disparity: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor, doffs: float = 0.0
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """(pixels with a stereo depth [B,1,H,W], Gaussians standing on one [B,N]) of the encoder's disparity:
        ``geometry.disparity_validity`` in the encoder's range, edge-replicated onto the canvas like z~, then
        ``composer.gaussian_validity``."""
        pixel_valid = disparity_validity(disparity, K[:, 0, 0], baseline, doffs,
                                         self.encoder.max_disparity(disparity.shape[-1]))
        canvas_valid = canvas.extend(pixel_valid.float(), self.params.padding) > 0.5
        return pixel_valid, gaussian_validity(canvas_valid, self.params.composer.back_layer)


def create_model(params: ModelParams, device: str | torch.device = "cpu", encoder: StereoEncoder | None = None
                 ) -> StereoGaussians:
    """Build the model; the encoder comes from the registry (``params.encoder``) unless one is given."""
    params.validate()
    if encoder is None:
        encoder = build_encoder(params.encoder, device)
    return StereoGaussians(params, encoder).to(device)


class Predictor:
    """A trained model ready for inference: ``predict(left, right, K, baseline) -> Prediction``. In float32 by
    default; with ``amp`` under bf16 autocast on CUDA, as ``train.render_targets`` trains it (measured on real
    photographs: float32 is the better of the two, and no slower for one pair; docs/benchmarks.md)."""

    def __init__(self, model: StereoGaussians, amp: bool = False) -> None:
        self.model = model.eval()
        self.amp = amp

    @property
    def resolution(self) -> int:
        return self.model.params.resolution

    def precision(self, device: str | torch.device) -> str:
        """What the convolutions compute in on ``device``: "bf16 autocast" (amp on CUDA) or "float32"."""
        return "bf16 autocast" if self.amp and torch.device(device).type == "cuda" else "float32"

    @torch.no_grad()
    def predict(self, left: torch.Tensor, right: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor,
                doffs: float = 0.0) -> Prediction:
        """The Prediction of a batch of pairs (Gaussians, depth, validity); see ``StereoGaussians.forward``."""
        with amp_autocast(left, self.amp):
            out = self.model(left, right, K, baseline, doffs)
        out.pixel_valid, out.valid = self.model.validity(out.disparity, K, baseline, doffs)
        return out


def load_predictor(checkpoint: str | Path, device: str | torch.device = "cpu", encoder_weights: str | None = None,
                   encoder_repo: str | None = None, encoder: str | None = None, amp: bool = False
                   ) -> Predictor:
    """Rebuild a model from a checkpoint written by ``sgmodel train`` (its ModelParams travel inside it);
    the frozen encoder is rebuilt from the registry with the checkpoint's settings, ``encoder_weights`` and
    ``encoder_repo`` over them (``--encoder-weights``, ``--encoder-repo``; ``encoder``, the ``--encoder`` flag,
    may only repeat the checkpoint's). ``amp``: bf16 autocast on CUDA (``--amp``) instead of float32, whatever
    precision the model was trained in. A checkpoint that is not ours, of another version, of weights that do not
    fit its model or that hold NaN raises ``CheckpointError`` naming the file."""
    from sgmodel.model.checkpoint import load_checkpoint, load_weights, model_params_of

    ckpt = load_checkpoint(checkpoint)
    params = model_params_of(ckpt, checkpoint)
    params.encoder = merge_encoder(params.encoder, encoder, encoder_weights, encoder_repo, checkpoint)
    model = create_model(params, device)
    load_weights(model, ckpt, checkpoint)
    return Predictor(model, amp=amp)
