"""From model-ready stereo pairs to Gaussians and rendered views: the one prediction path.

``sgmodel predict`` (a pair), its stereo video (``sgmodel.predict.video``), ``sgmodel bench predict --video`` and
the baselines of ``sgmodel eval`` all go through ``Reconstructor`` (a trained model, or a baseline of
``sgmodel.model.baselines`` on an encoder's disparity) and ``Scenes.render``.

Pixels without a valid stereo depth (``geometry.disparity_validity``: no match, occluded, outside the
encoder's range or beyond the depth clamps) produce no Gaussian: ``Scenes.valid`` marks the Gaussians that
stand on one (the model keeps SPEC section 7's fixed N, so its batch stays [B,N]); ``Scenes.scene`` drops
the others and ``Scenes.render`` renders with their opacity 0, which the rasteriser treats exactly as an
absent Gaussian (SPEC section 2, step 6: o exp(-sigma) < 1/255 touches no pixel). Forward-splat splats
no invalid pixel.

Everything is in the left camera's frame: OpenCV axes (x right, y down, z forward), metres, K in pixels.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import torch

from scenesplat_stereo.scene.gaussians import GaussianScene
from sgmodel.model import baselines
from sgmodel.model.geometry import depth_from_disparity, disparity_validity
from sgmodel.model.render import render_views
from sgmodel.predict.export import to_scene

#: Optional stage clock of ``Reconstructor.__call__``: called with a stage name after each stage.
Lap = Callable[[str], None]


def masked(gaussians: dict, valid: torch.Tensor) -> dict:
    """The Gaussians dict with the opacity of every Gaussian where ``valid`` [B,N] is False set to 0."""
    return {**gaussians, "opacities": gaussians["opacities"] * valid.to(gaussians["opacities"].dtype)}


@dataclass
class Scenes:
    """A batch of reconstructions from B pairs: left [B,3,H,W] in [0,1], K [B,3,3], depth z [B,1,H,W]
    (clipped), pixel_valid [B,1,H,W] bool; gaussians (the dict of sgmodel.model.render, [B,N]) and valid [B,N]
    bool, both None for forward-splat, which has no Gaussians."""

    left: torch.Tensor
    K: torch.Tensor
    depth: torch.Tensor
    pixel_valid: torch.Tensor
    gaussians: dict | None
    valid: torch.Tensor | None

    def in_frame(self, frame: Callable[[dict], dict] | None) -> Scenes:
        """These Scenes with their Gaussians moved by ``frame`` (None: as they are), e.g. into a raw rig's left
        camera frame (``Rectification.to_raw_frame``) for the scene files; render the original (its cameras
        are the rectified ones)."""
        if frame is None or self.gaussians is None:
            return self
        return dataclasses.replace(self, gaussians=frame(self.gaussians))

    def scene(self, index: int) -> GaussianScene:
        """Scene ``index`` with only its valid Gaussians, SH cut to the degree its content has."""
        if self.gaussians is None:
            raise ValueError("forward-splat has no Gaussians: it writes no scene")
        return to_scene(self.gaussians, index, self.valid[index])

    def focus(self, index: int) -> float:
        """Median valid depth of item ``index`` in metres (of every pixel when none is valid): the distance
        the novel views and the viewers' orbit centre look at."""
        z = self.depth[index, 0]
        valid = self.pixel_valid[index, 0]
        return float((z[valid] if valid.any() else z).median())

    def counts(self, index: int | None = None) -> tuple[int, int]:
        """(kept, produced): Gaussians of item ``index`` (None: of the whole batch) that stand on a stereo
        depth, and all of them (pixels for forward-splat)."""
        valid = self.valid if self.valid is not None else self.pixel_valid.flatten(1)
        chosen = valid if index is None else valid[index]
        return int(chosen.sum()), chosen.numel()

    def render(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int) -> torch.Tensor:
        """Each item into its T cameras: viewmats [B,T,4,4] (left camera to target), Ks [B,T,3,3] ->
        rgb [B,T,3,height,width] (black where nothing is seen; not clipped)."""
        if self.gaussians is None:
            return baselines.forward_splat(self.left, self.depth, self.K, viewmats, Ks, width, height,
                                           valid=self.pixel_valid)[0]
        return render_views(masked(self.gaussians, self.valid), viewmats, Ks, width, height)[0]


class Reconstructor:
    """Pairs -> ``Scenes`` with a trained model (``predictor``, a ``model.Predictor``) or a baseline
    (``method`` in ``baselines.METHODS`` with a frozen ``encoder``)."""

    def __init__(self, predictor=None, method: str | None = None, encoder=None) -> None:
        if (predictor is None) == (method is None) or (method is not None and encoder is None):
            raise ValueError("Reconstructor: give a predictor, or a method with its encoder")
        if method is not None and method not in baselines.METHODS:
            raise ValueError(f"Reconstructor: unknown method {method!r}; expected one of {baselines.METHODS}")
        self.predictor, self.method, self.encoder = predictor, method, encoder

    @property
    def name(self) -> str:
        """"model" or the baseline's name."""
        return self.method or "model"

    @torch.no_grad()
    def __call__(self, left: torch.Tensor, right: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor,
                 doffs: float = 0.0, lap: Lap | None = None) -> Scenes:
        """left/right [B,3,H,W] in [0,1], K [B,3,3] pixels, baseline [B] metres, doffs pixels (Middlebury's
        principal-point offset, the same for the batch) -> Scenes. ``lap(stage)`` after each stage:
        "predict" for the model; "encoder" then "compose" (naive-GS) for a baseline."""
        lap = lap or (lambda stage: None)
        if self.predictor is not None:
            out = self.predictor.predict(left, right, K, baseline, doffs)
            lap("predict")
            return Scenes(left, K, out.depth, out.pixel_valid, out.gaussians, out.valid)
        disparity = self.encoder(left, right).disparity.float()
        z = depth_from_disparity(disparity, K[:, 0, 0], baseline, doffs=doffs)
        pixel_valid = disparity_validity(disparity, K[:, 0, 0], baseline, doffs,
                                         self.encoder.max_disparity(left.shape[-1]))
        lap("encoder")
        if self.method == "forward-splat":
            return Scenes(left, K, z, pixel_valid, None, None)
        gaussians = baselines.naive_gs(left, z, K)
        lap("compose")
        return Scenes(left, K, z, pixel_valid, gaussians, pixel_valid.flatten(1))
