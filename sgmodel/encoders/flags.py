"""The encoder flags of every ``sgmodel`` command, and the one place where they become an encoder.

A command that makes one encoder (``predict``, ``eval``, ``train``, ``ablate``, ``bench train``, ``bench predict``)
calls ``add_encoder_arguments(parser)`` for ``--encoder NAME``, ``--encoder-weights PATH`` and ``--encoder-repo
PATH``, then ``encoder_params(args, base)``: the flags over ``base`` (a preset's or a checkpoint's
``EncoderParams``); naming another encoder than ``base`` starts from that encoder's defaults, and a checkpoint's
encoder cannot be replaced (its decoder was trained on that encoder's features). ``sgmodel bench encoders``
compares several, each written ``NAME[,weights=PATH][,repo=PATH]`` (``parse_encoder_spec``). ``build_encoder``
makes the frozen encoder (``sgmodel.encoders.create_encoder``). Bad flags raise ``EncoderFlagError`` (a
ValueError naming the flag); missing or unusable weights and checkouts a ``WeightsError`` naming the file.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from sgmodel.config import EncoderParams
from sgmodel.encoders import DEFAULT_ENCODER, EncoderFlagError, StereoEncoder, available_encoders, create_encoder

SPEC_KEYS = ("weights", "repo")


def add_encoder_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup,
                          default: str = DEFAULT_ENCODER) -> None:
    """``--encoder``, ``--encoder-weights``, ``--encoder-repo`` (``default`` says what none means, for the help)."""
    parser.add_argument("--encoder", help=f"frozen stereo encoder, one of {', '.join(available_encoders())} "
                                          f"(default {default}; docs/encoders.md)")
    parser.add_argument("--encoder-weights", help="the encoder's weights file (default: the fetched cache; for "
                                                  "foundation-stereo model_best_bp2.pth with cfg.yaml beside it)")
    parser.add_argument("--encoder-repo", help="your checkout of the encoder's code (foundation-stereo, "
                                               "fast-foundation-stereo: the folder holding core/)")


def merge_encoder(base: EncoderParams | None, name: str | None = None, weights: str | None = None,
                  repo: str | None = None, checkpoint: str | Path | None = None) -> EncoderParams:
    """``base`` with the given name, weights and repo over it. Another name than ``base.name`` starts from that
    encoder's defaults (nothing of ``base`` carries over), except for a ``checkpoint``'s encoder: an error."""
    base = base or EncoderParams(name=DEFAULT_ENCODER)
    if name is not None and name != base.name:
        if checkpoint is not None:
            raise EncoderFlagError(f"--encoder {name}: checkpoint {checkpoint} was trained with encoder "
                                   f"{base.name!r} (its decoder expects that encoder's features); leave --encoder out")
        base = EncoderParams(name=name)
    return EncoderParams(name=base.name, weights=weights if weights is not None else base.weights,
                         repo=repo if repo is not None else base.repo)


def encoder_params(args: argparse.Namespace, base: EncoderParams | None = None,
                   checkpoint: str | Path | None = None) -> EncoderParams:
    """The encoder the flags of ``add_encoder_arguments`` ask for, over ``base`` (see ``merge_encoder``)."""
    return merge_encoder(base, getattr(args, "encoder", None), getattr(args, "encoder_weights", None),
                         getattr(args, "encoder_repo", None), checkpoint)


def parse_encoder_spec(text: str) -> EncoderParams:
    """``NAME[,weights=PATH][,repo=PATH]`` (an item of ``--encoders``) -> EncoderParams (paths may not contain
    commas)."""
    flag = "--encoders"
    name, *options = text.split(",")
    name = name.strip()
    if not name:
        raise EncoderFlagError(f"{flag} {text!r}: expected NAME[,weights=PATH][,repo=PATH]")
    values: dict[str, str] = {}
    for option in options:
        key, sep, value = option.partition("=")
        key = key.strip()
        if not sep or key not in SPEC_KEYS or not value or key in values:
            raise EncoderFlagError(f"{flag} {text!r}: {option!r} is not one of weights=PATH, repo=PATH (each once; "
                                   f"expected NAME[,weights=PATH][,repo=PATH])")
        values[key] = value
    return EncoderParams(name=name, weights=values.get("weights"), repo=values.get("repo"))


def encoder_label(params: EncoderParams, others: list[EncoderParams]) -> str:
    """The encoder's name, with its weights file where ``others`` hold the same name with other weights."""
    if params.weights is None or sum(o.name == params.name for o in others) < 2:
        return params.name
    return f"{params.name} ({Path(params.weights).parent.name}/{Path(params.weights).name})"


def build_encoder(params: EncoderParams, device: str | torch.device = "cpu") -> StereoEncoder:
    """The frozen encoder ``params`` names, on ``device``."""
    return create_encoder(params.name, params.weights, params.repo, device)
