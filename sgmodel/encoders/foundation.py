"""``foundation-stereo`` and ``fast-foundation-stereo``: the paper's frozen encoders (appendix A), as
adapters around the user's own checkouts of NVlabs/FoundationStereo and NVlabs/Fast-FoundationStereo.

Their licence forbids copying their code here, so nothing of theirs is in this package: ``repo`` is the
path of the user's checkout (the folder holding ``core/foundation_stereo.py``; ``--encoder-repo``), imported
as its demo scripts do but pinned to that checkout (``sgmodel.encoders.checkout``: both encoders can live in
one process, in either order) and built offline (no socket, torch.hub served from the checkout, timm without
downloads); ``weights`` is the checkpoint (``--encoder-weights``). Every failure while importing, building,
loading or test-running them is one ``WeightsError`` line naming the flag and file.

- ``foundation-stereo``: ``core.foundation_stereo.FoundationStereo(args)`` with ``args`` read from the
  ``cfg.yaml`` beside the checkpoint (``model_best_bp2.pth``; ``vit_size`` defaults to ``vitl`` as in their
  demo), its DINOv2 built from the checkout's vendored ``dinov2/`` (their ``depth_anything/dpt.py`` asks
  torch.hub for ``facebookresearch/dinov2``), the weights loaded from the checkpoint's ``"model"`` entry
  (``weights_only=True``). Forward: ``model(image1, image2, iters=32, test_mode=True)`` (their demo's 32
  updates). Features (appendix A: image, context and recurrent features), captured by forward hooks: the
  left view's image features (``model.feature``'s ``[x4, x8, x16, x32]``), then for each GRU level
  (``args.n_gru_layers``; ``model.cnet`` returns all three whatever ``num_layers`` says) the context features
  relu(inp) and the hidden state after the last update (``model.update_block`` rewrites its ``net`` list in
  place; the hook copies it per call), concatenated per scale in this order.
- ``fast-foundation-stereo``: the serialised model file of their release (``model_best_bp2_serialize.pth``,
  a pickled ``core.foundation_stereo.FastFoundationStereo``, loaded with ``weights_only=False``: only give a
  file you trust), with ``args.valid_iters = 8`` and ``args.max_disp = 192`` as their demo sets them (its
  ``--valid_iters`` and ``--max_disp`` defaults, which it applies over ``cfg.yaml``), forward
  ``model(image1, image2, iters=8, test_mode=True, optimize_build_volume="pytorch1")`` (the paper's 8
  updates, PyTorch cost volume). Features (appendix A: left image features; the decoder adds RGB-D itself):
  ``model.feature``'s output for the left view.

Their releases are pruned: layer widths differ from the constants in their code (``feature.d_out`` and the
like). So the feature scales and channel counts are measured, not read from attributes: at construction the
loaded model runs once (one update) on a 32 x 32 pair, and each captured map's scale is the input size over its
own. Both networks take RGB in [0, 255] (they apply the ImageNet normalisation themselves), so inputs in
[0, 1] are scaled by 255; images are padded at the bottom and right to a multiple of 32 (edge replication)
and outputs cropped back. Disparity: pixels of the input, left reference.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from sgmodel.encoders.base import EncoderOutput, StereoEncoder, crop_to, pad_to_multiple
from sgmodel.encoders.checkout import Checkout, one_line
from sgmodel.weights import WeightsError, sha256_file

PAD_MULTIPLE = 32  # their demos pad to a multiple of 32
FOUNDATION_ITERS = 32  # FoundationStereo demo's valid_iters
FAST_FOUNDATION_ITERS = 8  # paper appendix A: eight recurrent updates (their demo's default too)
FAST_FOUNDATION_MAX_DISP = 192  # Fast-FoundationStereo demo's --max_disp default, set on the loaded model
PROBE_SIZE = PAD_MULTIPLE  # pixels: the pair the loaded model runs once to measure its feature maps
REPO_FLAG, WEIGHTS_FLAG = "--encoder-repo", "--encoder-weights"
_CHECKOUTS: dict[tuple[Path, str], Checkout] = {}


class _Config(dict):
    """A dict with attribute access, standing in for OmegaConf's DictConfig when omegaconf is absent."""

    def __getattr__(self, key: str) -> Any:
        try:
            return self[key]
        except KeyError as e:
            raise AttributeError(key) from e

    def __setattr__(self, key: str, value: Any) -> None:
        self[key] = value


def checkout(repo: str | os.PathLike | None, name: str, project: str, weights_hint: str) -> Checkout:
    """The pinned checkout at ``repo`` (one per folder, project and process), or a WeightsError saying what to pass."""
    if repo is None:
        raise WeightsError(f"encoder {name!r} needs your checkout of NVlabs/{project}: pass {REPO_FLAG} PATH "
                           f"(the folder with core/foundation_stereo.py) and {WEIGHTS_FLAG} PATH ({weights_hint})")
    root = Path(repo).resolve()
    if not (root / "core" / "foundation_stereo.py").is_file():
        raise WeightsError(f"{REPO_FLAG} {repo}: no core/foundation_stereo.py there (expected a checkout of "
                           f"NVlabs/{project})")
    if (root, project) not in _CHECKOUTS:
        _CHECKOUTS[root, project] = Checkout(root, project)
    return _CHECKOUTS[root, project]


def _weights_path(weights: str | os.PathLike | None, name: str, hint: str) -> Path:
    if weights is None:
        raise WeightsError(f"encoder {name!r} needs its checkpoint: pass {WEIGHTS_FLAG} PATH ({hint})")
    path = Path(weights)
    if not path.is_file():
        raise WeightsError(f"{WEIGHTS_FLAG} {path}: no such file")
    return path


def load_config(path: Path) -> Any:
    """FoundationStereo's ``cfg.yaml`` (``vit_size`` defaulting to ``vitl``) as their demo reads it: an OmegaConf
    DictConfig, or a dict with attribute access when omegaconf is absent; a WeightsError naming the file."""
    import yaml

    if not path.is_file():
        raise WeightsError(f"{WEIGHTS_FLAG} {path.parent}: no cfg.yaml beside the checkpoint (FoundationStereo "
                           f"releases ship one in each model folder)")
    try:
        cfg = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise WeightsError(f"{WEIGHTS_FLAG} {path}: not a readable cfg.yaml ({one_line(e)})") from e
    if not isinstance(cfg, dict):
        raise WeightsError(f"{WEIGHTS_FLAG} {path}: cfg.yaml holds a {type(cfg).__name__}, expected a mapping")
    cfg.setdefault("vit_size", "vitl")
    try:
        from omegaconf import OmegaConf
    except ImportError:
        return _Config(cfg)
    return OmegaConf.create(cfg)


def _set(args: Any, key: str, value: Any) -> None:
    """``args.key = value`` on their OmegaConf config (or a plain mapping / namespace)."""
    if isinstance(args, MutableMapping):
        args[key] = value
    else:
        setattr(args, key, value)


def by_stride(maps: list[Tensor], size: tuple[int, int], name: str) -> dict[int, list[Tensor]]:
    """Maps [B,C,h,w] of an input of ``size`` (H, W) grouped by their stride s = H / h = W / w, in order."""
    grouped: dict[int, list[Tensor]] = {}
    for m in maps:
        s = size[0] // m.shape[-2]
        if (m.shape[-2] * s, m.shape[-1] * s) != tuple(size):
            raise RuntimeError(f"{name}: a feature map of {tuple(m.shape)} is not a whole stride of the "
                               f"{size[1]}x{size[0]} input")
        grouped.setdefault(s, []).append(m)
    return grouped


class _HookedStereo(StereoEncoder):
    """Shared forward: scale to [0,255], pad, run with hooks recording, crop, group maps per scale."""

    iters: int

    def _run(self, left: Tensor, right: Tensor, iters: int) -> Tensor:
        raise NotImplementedError

    def _maps(self, batch: int) -> list[Tensor]:
        """The left view's maps recorded by the hooks during the last ``_run``, in feature order."""
        raise NotImplementedError

    def encode(self, left: Tensor, right: Tensor) -> EncoderOutput:
        h, w = left.shape[-2:]
        disparity, grouped = self._forward(left, right, self.iters)
        features = [crop_to(torch.cat(grouped[s], 1).float(), h, w, s) for s in self.feature_scales]
        return EncoderOutput(disparity=crop_to(disparity.float(), h, w), features=features)

    def _forward(self, left: Tensor, right: Tensor, iters: int) -> tuple[Tensor, dict[int, list[Tensor]]]:
        left = pad_to_multiple(left.float() * 255, PAD_MULTIPLE)
        right = pad_to_multiple(right.float() * 255, PAD_MULTIPLE)
        self._record: dict[str, Any] = {}
        try:
            disparity = self._run(left, right, iters)
            maps = self._maps(left.shape[0])
        finally:
            self._record = {}
        return disparity, by_stride(maps, tuple(left.shape[-2:]), self.name)

    def _hook(self, module: nn.Module, key: str, keep=lambda out: out) -> None:
        module.register_forward_hook(lambda _m, _i, out: self._record.__setitem__(key, keep(out)))

    def _measure(self, weights: Path) -> None:
        """``feature_scales`` and ``feature_channels`` as the loaded (frozen) model computes them: one run with
        one update on a PROBE_SIZE x PROBE_SIZE pair."""
        pair = torch.rand(2, 1, 3, PROBE_SIZE, PROBE_SIZE, generator=torch.Generator().manual_seed(0))
        try:
            with torch.no_grad():
                _, grouped = self._forward(pair[0], pair[1], 1)
        except Exception as e:  # noqa: BLE001 - a model that cannot run is one user error
            raise WeightsError(f"{WEIGHTS_FLAG} {weights}: the loaded {self.name} model fails on a {PROBE_SIZE}x"
                               f"{PROBE_SIZE} test pair ({one_line(e)})") from e
        self.feature_scales = tuple(sorted(grouped))
        self.feature_channels = tuple(sum(m.shape[1] for m in grouped[s]) for s in self.feature_scales)


class FoundationStereoEncoder(_HookedStereo):
    """Frozen FoundationStereo from the user's checkout; see the module docstring."""

    name = "foundation-stereo"

    def __init__(self, repo: str | os.PathLike | None, weights: str | os.PathLike | None,
                 iters: int = FOUNDATION_ITERS):
        super().__init__()
        hint = "model_best_bp2.pth with its cfg.yaml beside it"
        code = checkout(repo, self.name, "FoundationStereo", hint)
        path = _weights_path(weights, self.name, hint)
        args = load_config(path.parent / "cfg.yaml")
        try:
            with code.building(REPO_FLAG):
                model = code.import_module("core.foundation_stereo", REPO_FLAG).FoundationStereo(args)
        except WeightsError:
            raise
        except Exception as e:  # noqa: BLE001 - whatever their constructor raises is one user error
            raise WeightsError(f"{REPO_FLAG} {repo}: building FoundationStereo with {path.parent / 'cfg.yaml'} "
                               f"failed ({one_line(e)})") from e
        try:
            model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True)["model"])
        except Exception as e:  # noqa: BLE001 - any unreadable or mismatched checkpoint is one user error
            raise WeightsError(f"{WEIGHTS_FLAG} {path}: not a FoundationStereo checkpoint for {path.parent}/cfg.yaml "
                               f"({one_line(e)})") from e
        self.model = model
        self.weights_sha256 = sha256_file(path)
        self.iters = iters
        self.levels = int(args.n_gru_layers)
        self._hook(self.model.feature, "feature")
        self._hook(self.model.cnet, "cnet")
        self._hook(self.model.update_block, "update", keep=lambda out: list(out[0]))
        self.freeze()
        self._measure(path)

    def _run(self, left: Tensor, right: Tensor, iters: int) -> Tensor:
        return self.model(left, right, iters=iters, test_mode=True)

    def _maps(self, batch: int) -> list[Tensor]:
        image, _vit = self._record["feature"]
        cnet, hidden = self._record["cnet"], self._record["update"]
        maps = [f[:batch] for f in image]
        for j in range(self.levels):
            maps += [torch.relu(cnet[j][1]), hidden[j]]
        return maps


class FastFoundationStereoEncoder(_HookedStereo):
    """Frozen Fast-FoundationStereo from the user's checkout; see the module docstring."""

    name = "fast-foundation-stereo"

    def __init__(self, repo: str | os.PathLike | None, weights: str | os.PathLike | None,
                 iters: int = FAST_FOUNDATION_ITERS, max_disp: int = FAST_FOUNDATION_MAX_DISP):
        super().__init__()
        hint = "the serialised model file, e.g. weights/23-36-37/model_best_bp2_serialize.pth"
        code = checkout(repo, self.name, "Fast-FoundationStereo", hint)
        path = _weights_path(weights, self.name, hint)
        try:
            with code.building(REPO_FLAG):
                module = code.import_module("core.foundation_stereo", REPO_FLAG)
                model = torch.load(path, map_location="cpu", weights_only=False)
        except WeightsError:
            raise
        except Exception as e:  # noqa: BLE001 - any unreadable file is one user error
            raise WeightsError(f"{WEIGHTS_FLAG} {path}: not a serialised Fast-FoundationStereo model of {repo} "
                               f"({one_line(e)})") from e
        if not isinstance(model, module.FastFoundationStereo):
            raise WeightsError(f"{WEIGHTS_FLAG} {path}: holds a {type(model).__name__}, expected the serialised "
                               f"FastFoundationStereo of their release")
        self.model = model
        self.weights_sha256 = sha256_file(path)
        self.iters = iters
        _set(self.model.args, "valid_iters", iters)
        _set(self.model.args, "max_disp", max_disp)
        self._hook(self.model.feature, "feature")
        self.freeze()
        self._measure(path)

    def _run(self, left: Tensor, right: Tensor, iters: int) -> Tensor:
        return self.model(left, right, iters=iters, test_mode=True, optimize_build_volume="pytorch1")

    def _maps(self, batch: int) -> list[Tensor]:
        return [f[:batch] for f in self._record["feature"]]
