"""Frozen stereo encoders by name (SPEC section 7, "Encoder").

``create_encoder(name, weights=None, repo=None, device="cpu")`` builds one; ``ENCODERS`` maps each
registered name to its factory ``(weights, repo) -> StereoEncoder``; ``register_encoder`` adds one.
Registered: ``psmnet-kitti`` (the default; PSMNet with the KITTI-2015 weights), ``sgbm`` (OpenCV
semi-global matching + WLS, no learned features), ``foundation-stereo`` and ``fast-foundation-stereo``
(adapters to the user's own checkouts of NVlabs' code, ``repo`` = its path, ``weights`` = checkpoint).
``sgmodel.encoders.flags`` turns the command-line flags into one (every command uses it).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from sgmodel.encoders.base import EncoderOutput, StereoEncoder

EncoderFactory = Callable[[str | None, str | None], StereoEncoder]
ENCODERS: dict[str, EncoderFactory] = {}
DEFAULT_ENCODER = "psmnet-kitti"


class EncoderFlagError(ValueError):
    """An encoder flag that cannot be used (unknown name, an option the encoder does not take); names the flag."""


def register_encoder(name: str) -> Callable[[EncoderFactory], EncoderFactory]:
    """Decorator: register ``factory(weights, repo) -> StereoEncoder`` under ``name``."""

    def add(factory: EncoderFactory) -> EncoderFactory:
        if name in ENCODERS:
            raise ValueError(f"encoder {name!r} is already registered")
        ENCODERS[name] = factory
        return factory

    return add


def available_encoders() -> list[str]:
    return sorted(ENCODERS)


def create_encoder(name: str, weights: str | None = None, repo: str | None = None,
                   device: str | torch.device = "cpu") -> StereoEncoder:
    """The frozen encoder ``name`` on ``device``; unknown names give an EncoderFlagError listing the known ones,
    missing weights or repositories a ``sgmodel.weights.WeightsError`` saying how to provide them."""
    if name not in ENCODERS:
        raise EncoderFlagError(f"--encoder {name}: unknown encoder; available: {', '.join(available_encoders())}")
    return ENCODERS[name](weights, repo).to(device)


@register_encoder("psmnet-kitti")
def _psmnet(weights: str | None, repo: str | None) -> StereoEncoder:
    from sgmodel.encoders.psmnet import PSMNetEncoder

    _no_repo("psmnet-kitti", repo)
    return PSMNetEncoder(weights)


@register_encoder("sgbm")
def _sgbm(weights: str | None, repo: str | None) -> StereoEncoder:
    from sgmodel.encoders.sgbm import SGBMEncoder

    _no_repo("sgbm", repo)
    if weights is not None:
        raise EncoderFlagError("--encoder-weights: encoder 'sgbm' is classical and takes no weights")
    return SGBMEncoder()


@register_encoder("foundation-stereo")
def _foundation(weights: str | None, repo: str | None) -> StereoEncoder:
    from sgmodel.encoders.foundation import FoundationStereoEncoder

    return FoundationStereoEncoder(repo, weights)


@register_encoder("fast-foundation-stereo")
def _fast_foundation(weights: str | None, repo: str | None) -> StereoEncoder:
    from sgmodel.encoders.foundation import FastFoundationStereoEncoder

    return FastFoundationStereoEncoder(repo, weights)


def _no_repo(name: str, repo: str | None) -> None:
    if repo is not None:
        raise EncoderFlagError(f"--encoder-repo: encoder {name!r} is built in and takes no code checkout")


__all__ = ["ENCODERS", "DEFAULT_ENCODER", "EncoderFlagError", "EncoderOutput", "StereoEncoder", "available_encoders",
           "create_encoder", "register_encoder"]
