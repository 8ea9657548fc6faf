"""The checkpoint file format: one owner for writing and reading ``RUN/checkpoints/*.pt``.

A checkpoint is a plain ``torch.save`` dict (PyTorch convention; load with ``weights_only=True``):

- ``format``: ``CHECKPOINT_FORMAT``; ``model_params``: ``ModelParams.to_dict()`` (rebuilds the model);
- ``model``: the trainable ``state_dict`` (decoder + predictor; never the frozen encoder);
- ``encoder``: {name, sha256} of the frozen encoder it was trained with, for the record;
- ``train_params``, ``step`` (optimiser steps done), ``best_val_psnr``, ``best_step``;
- ``optimizer``, ``scheduler``: their ``state_dict``s; ``rng``: torch/CUDA generator states
  (so a resumed run continues exactly; the data order is a function of (seed, step)).

A weights-only checkpoint (``pack_checkpoint``; the ``sgmodel pack`` command writes one, and the model shipped in
the package is one) keeps ``format``, ``model_params``, ``model`` (optionally in bfloat16 or float16: loading casts it
back to the model's float32), ``encoder``, ``step``, ``best_val_psnr``, ``best_step`` and ``train_params`` reduced to
``amp`` (the training run's precision, for the record: inference runs in float32 unless asked for bf16); it has no
optimiser, scheduler or RNG state, so a run cannot resume from it.

Writes are atomic (a temporary file renamed over the old one), so an interrupted save never leaves a
half-written ``last.pt``. Reading refuses (``CheckpointError``, naming the file) a file that is not a
checkpoint, one of another format version, and one whose weights hold NaN or infinity (a diverged run:
``sgmodel train`` never writes one, and ``eval``/``predict`` must not use one).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from scenesplat_stereo.common.files import atomic_write_bytes
from sgmodel.config import ModelParams

CHECKPOINT_FORMAT = "sgmodel-checkpoint-v1"
REQUIRED = ("format", "model_params", "model", "step")


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or not ours; the message names the file."""


def checkpoint_bytes(state: dict[str, Any]) -> bytes:
    """The file of ``state`` (with ``format`` added): what ``save_checkpoint`` writes."""
    buf = io.BytesIO()
    torch.save({"format": CHECKPOINT_FORMAT, **state}, buf)
    return buf.getvalue()


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Atomically write ``state`` (with ``format`` added) to ``path``."""
    atomic_write_bytes(Path(path), checkpoint_bytes(state))


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read and check a checkpoint; CheckpointError naming the file and the field otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises many types for a corrupt or foreign file
        raise CheckpointError(f"{path}: not a readable PyTorch checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path}: expected a dict, found {type(ckpt).__name__}")
    missing = [k for k in REQUIRED if k not in ckpt]
    if missing:
        raise CheckpointError(f"{path}: missing fields {missing} (not written by `sgmodel train`?)")
    if ckpt["format"] != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: format {ckpt['format']!r} (another version of sgmodel); this version "
                              f"reads {CHECKPOINT_FORMAT!r}")
    if not isinstance(ckpt["model"], dict):
        raise CheckpointError(f"{path}: field 'model' is a {type(ckpt['model']).__name__}, not a state dict")
    bad = nonfinite_weights(ckpt["model"])
    if bad:
        raise CheckpointError(f"{path}: {len(bad)} weight tensors hold NaN or infinity (e.g. {bad[0]}): a "
                              f"diverged model; use a checkpoint from before the divergence")
    return ckpt


def model_params_of(ckpt: dict[str, Any], path: str | Path) -> ModelParams:
    """The ``ModelParams`` a checkpoint was trained with; CheckpointError naming the file when its record is
    of another version (unknown or missing fields)."""
    try:
        return ModelParams.from_dict(ckpt["model_params"])
    except (TypeError, ValueError, AttributeError) as e:
        raise CheckpointError(f"{path}: its model_params do not fit this version of sgmodel ({e})") from None


def load_weights(model: torch.nn.Module, ckpt: dict[str, Any], path: str | Path) -> None:
    """``model.load_state_dict(ckpt["model"])``; CheckpointError naming the file and the first mismatched
    weights when the checkpoint is of another architecture."""
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as e:
        detail = [line.strip() for line in str(e).splitlines()[1:] if line.strip()][:2]
        raise CheckpointError(f"{path}: its weights do not fit this model ({'; '.join(detail)[:300]})") from None


def nonfinite_weights(state: dict[str, Any]) -> list[str]:
    """Names of the floating-point tensors of a state dict that hold NaN or infinity."""
    if not isinstance(state, dict):
        return []
    return [k for k, v in state.items() if torch.is_tensor(v) and v.is_floating_point() and not torch.isfinite(v).all()]


PACKED_FIELDS = ("model_params", "encoder", "step", "best_val_psnr", "best_step")
PACK_DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


def pack_checkpoint(src: str | Path, dtype: str = "fp32") -> dict[str, Any]:
    """The weights-only checkpoint of ``src``, its floating-point weights in ``dtype`` (a key of
    ``PACK_DTYPES``), to write with ``checkpoint_bytes`` (``sgmodel pack``). CheckpointError naming the file for a
    bad ``src``; a weight that does not fit ``dtype`` (beyond its range) is refused rather than written as
    infinity."""
    ckpt = load_checkpoint(src)
    model_params_of(ckpt, src)  # a checkpoint this version can rebuild
    to = PACK_DTYPES[dtype]
    weights = {k: v.to(to) if torch.is_tensor(v) and v.is_floating_point() else v for k, v in ckpt["model"].items()}
    bad = nonfinite_weights(weights)
    if bad:
        raise CheckpointError(f"{src}: {len(bad)} weight tensors do not fit {dtype} (e.g. {bad[0]}): pack as fp32")
    packed = {k: ckpt[k] for k in PACKED_FIELDS if k in ckpt}
    packed |= {"model": weights, "train_params": {"amp": bool(ckpt.get("train_params", {}).get("amp", True))}}
    return {"format": CHECKPOINT_FORMAT, **packed}
