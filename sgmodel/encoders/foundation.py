"""``foundation-stereo`` and ``fast-foundation-stereo``: the paper's frozen encoders (appendix A), as
adapters around the user's own checkouts of NVlabs/FoundationStereo and NVlabs/Fast-FoundationStereo.

Their licence forbids copying their code here, so nothing of theirs is in this package: ``repo`` is the
path of the user's checkout (the folder holding ``core/foundation_stereo.py``; ``--encoder-repo``), put
first on ``sys.path`` and imported as its demo scripts do; ``weights`` is the checkpoint
(``--encoder-weights``). Both repositories name their package ``core``; a ``core`` imported from another
place is dropped from ``sys.modules`` first, so one process can hold one of them at a time.

- ``foundation-stereo``: ``core.foundation_stereo.FoundationStereo(args)`` with ``args`` read from the
  ``cfg.yaml`` beside the checkpoint (``model_best_bp2.pth``; ``vit_size`` defaults to ``vitl`` as in
  their demo), the weights loaded from the checkpoint's ``"model"`` entry (``weights_only=True``).
  Construction is kept offline: ``HF_HUB_OFFLINE=1`` and, when ``timm`` is installed, ``timm.create_model``
  with ``pretrained=False`` (every weight comes from the checkpoint). Forward: ``model(image1, image2,
  iters=32, test_mode=True)`` (their demo's 32 updates). Features (appendix A: image features at four
  scales, context features and the final recurrent states), captured by forward hooks, one map per
  scale s in (4, 8, 16, 32), the concatenation in this order of what exists at that scale:
  the left view's image features (``model.feature``'s first output, d_out[i] channels at 4 * 2^i),
  the context features relu(inp) of each GRU level (``model.cnet``, hidden_dims[i] channels at 4 * 2^i,
  i < n_gru_layers) and the hidden states of each GRU level after the last update
  (``model.update_block``'s first output, hidden_dims[i] channels).
- ``fast-foundation-stereo``: the serialised model file of their release (``model_best_bp2_serialize.pth``,
  a pickled ``core.foundation_stereo.FastFoundationStereo``, loaded with ``weights_only=False``: only
  give a file you trust), forward ``model(image1, image2, iters=8, test_mode=True,
  optimize_build_volume="pytorch1")`` (the paper's 8 updates, PyTorch cost volume). Features (appendix A:
  left image features; the decoder adds RGB-D itself): ``model.feature``'s output for the left view at
  s in (4, 8, 16, 32), d_out[i] channels.

Both take RGB in [0, 255] (they apply the ImageNet normalisation themselves), so inputs in [0, 1] are
scaled by 255; images are padded at the bottom and right to a multiple of 32 (edge replication) and
outputs cropped back. Disparity: pixels of the input, left reference.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from sgmodel.encoders.base import EncoderOutput, StereoEncoder, crop_to, pad_to_multiple
from sgmodel.weights import WeightsError, sha256_file

PAD_MULTIPLE = 32  # their demos pad to a multiple of 32
FOUNDATION_ITERS = 32  # FoundationStereo demo's valid_iters
FAST_FOUNDATION_ITERS = 8  # paper appendix A: eight recurrent updates
SCALES = (4, 8, 16, 32)


class _Config(dict):
    """A dict with attribute access, standing in for OmegaConf's DictConfig when omegaconf is absent."""

    def __getattr__(self, key: str) -> Any:
        try:
            return self[key]
        except KeyError as e:
            raise AttributeError(key) from e

    def __setattr__(self, key: str, value: Any) -> None:
        self[key] = value


def _import_repo(repo: str | os.PathLike | None, name: str, project: str, weights_hint: str):
    """``core.foundation_stereo`` of the checkout at ``repo``, or a WeightsError saying what to pass."""
    if repo is None:
        raise WeightsError(f"encoder {name!r} needs your checkout of NVlabs/{project}: pass --encoder-repo PATH "
                           f"(the folder with core/foundation_stereo.py) and --encoder-weights PATH ({weights_hint})")
    root = Path(repo).resolve()
    if not (root / "core" / "foundation_stereo.py").is_file():
        raise WeightsError(f"--encoder-repo {repo}: no core/foundation_stereo.py there (expected a checkout of "
                           f"NVlabs/{project})")
    for mod in [m for m in sys.modules if m == "core" or m.startswith("core.") or m == "Utils"]:
        file = getattr(sys.modules[mod], "__file__", None) or ""
        if not Path(file).resolve().is_relative_to(root):
            del sys.modules[mod]
    if str(root) in sys.path:
        sys.path.remove(str(root))
    sys.path.insert(0, str(root))
    try:
        return importlib.import_module("core.foundation_stereo")
    except ImportError as e:
        raise WeightsError(f"--encoder-repo {repo}: importing core/foundation_stereo.py failed ({e}); install "
                           f"the requirements of NVlabs/{project} in this environment") from e


def _weights_path(weights: str | os.PathLike | None, name: str, hint: str) -> Path:
    if weights is None:
        raise WeightsError(f"encoder {name!r} needs its checkpoint: pass --encoder-weights PATH ({hint})")
    path = Path(weights)
    if not path.is_file():
        raise WeightsError(f"--encoder-weights {path}: no such file")
    return path


@contextlib.contextmanager
def _offline():
    """No model-hub downloads while their modules are built: every weight comes from the checkpoint."""
    old = os.environ.get("HF_HUB_OFFLINE")
    os.environ["HF_HUB_OFFLINE"] = "1"
    timm = sys.modules.get("timm") or _try_import("timm")
    create = getattr(timm, "create_model", None)
    if create is not None:
        timm.create_model = lambda *a, **k: create(*a, **{**k, "pretrained": False})
    try:
        yield
    finally:
        if create is not None:
            timm.create_model = create
        if old is None:
            os.environ.pop("HF_HUB_OFFLINE", None)
        else:
            os.environ["HF_HUB_OFFLINE"] = old


def _try_import(module: str):
    try:
        return importlib.import_module(module)
    except ImportError:
        return None


def _load_config(path: Path) -> Any:
    import yaml

    if not path.is_file():
        raise WeightsError(f"--encoder-weights {path.parent}: no cfg.yaml beside the checkpoint (FoundationStereo "
                           f"releases ship one in each model folder)")
    cfg = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    cfg.setdefault("vit_size", "vitl")
    omegaconf = _try_import("omegaconf")
    return omegaconf.OmegaConf.create(cfg) if omegaconf is not None else _Config(cfg)


class _HookedStereo(StereoEncoder):
    """Shared forward: scale to [0,255], pad, run with hooks recording, crop, group maps per scale."""

    iters: int

    def _run(self, left: Tensor, right: Tensor) -> Tensor:
        raise NotImplementedError

    def _maps(self, batch: int) -> dict[int, list[Tensor]]:
        raise NotImplementedError

    def encode(self, left: Tensor, right: Tensor) -> EncoderOutput:
        h, w = left.shape[-2:]
        self._record: dict[str, Any] = {}
        disparity = self._run(pad_to_multiple(left.float() * 255, PAD_MULTIPLE),
                              pad_to_multiple(right.float() * 255, PAD_MULTIPLE))
        maps = self._maps(left.shape[0])
        features = [crop_to(torch.cat(maps[s], 1).float(), h, w, s) for s in self.feature_scales]
        self._record = {}
        return EncoderOutput(disparity=crop_to(disparity.float(), h, w), features=features)

    def _hook(self, module: nn.Module, key: str) -> None:
        module.register_forward_hook(lambda _m, _i, out: self._record.__setitem__(key, out))


class FoundationStereoEncoder(_HookedStereo):
    """Frozen FoundationStereo from the user's checkout; see the module docstring."""

    name = "foundation-stereo"
    feature_scales = SCALES

    def __init__(self, repo: str | os.PathLike | None, weights: str | os.PathLike | None,
                 iters: int = FOUNDATION_ITERS):
        super().__init__()
        hint = "model_best_bp2.pth with its cfg.yaml beside it"
        module = _import_repo(repo, self.name, "FoundationStereo", hint)
        path = _weights_path(weights, self.name, hint)
        args = _load_config(path.parent / "cfg.yaml")
        with _offline():
            self.model = module.FoundationStereo(args)
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
            self.model.load_state_dict(ckpt["model"])
        except Exception as e:  # noqa: BLE001 - any unreadable or mismatched checkpoint is one user error
            raise WeightsError(f"--encoder-weights {path}: not a FoundationStereo checkpoint for {path.parent}/cfg.yaml "
                               f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from e
        self.weights_sha256 = sha256_file(path)
        self.iters = iters
        self.levels = int(args.n_gru_layers)
        self.first_scale = 2 ** int(args.get("n_downsample", 2))
        d_out, hidden = list(self.model.feature.d_out), list(args.hidden_dims)
        self.feature_channels = tuple(
            d_out[i] + sum(2 * hidden[j] for j in range(self.levels) if self.first_scale * 2 ** j == s)
            for i, s in enumerate(SCALES))
        self._hook(self.model.feature, "feature")
        self._hook(self.model.cnet, "cnet")
        self._hook(self.model.update_block, "update")
        self.freeze()

    def _run(self, left: Tensor, right: Tensor) -> Tensor:
        return self.model(left, right, iters=self.iters, test_mode=True)

    def _maps(self, batch: int) -> dict[int, list[Tensor]]:
        maps: dict[int, list[Tensor]] = {s: [f[:batch]] for s, f in zip(SCALES, self._record["feature"][0])}
        hidden = self._record["update"][0]
        for j, (ctx, state) in enumerate(zip(list(self._record["cnet"])[: self.levels], hidden)):
            s = self.first_scale * 2 ** j
            maps[s] += [torch.relu(ctx[1]), state]
        return maps


class FastFoundationStereoEncoder(_HookedStereo):
    """Frozen Fast-FoundationStereo from the user's checkout; see the module docstring."""

    name = "fast-foundation-stereo"
    feature_scales = SCALES

    def __init__(self, repo: str | os.PathLike | None, weights: str | os.PathLike | None,
                 iters: int = FAST_FOUNDATION_ITERS):
        super().__init__()
        hint = "the serialised model file, e.g. weights/23-36-37/model_best_bp2_serialize.pth"
        module = _import_repo(repo, self.name, "Fast-FoundationStereo", hint)
        path = _weights_path(weights, self.name, hint)
        try:
            with _offline():
                model = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001
            raise WeightsError(f"--encoder-weights {path}: not a serialised Fast-FoundationStereo model "
                               f"({type(e).__name__}: {e})") from e
        if not isinstance(model, module.FastFoundationStereo):
            raise WeightsError(f"--encoder-weights {path}: holds a {type(model).__name__}, expected the serialised "
                               f"FastFoundationStereo of their release")
        self.model = model
        self.weights_sha256 = sha256_file(path)
        self.iters = iters
        self.model.args.valid_iters = iters
        self.feature_channels = tuple(self.model.feature.d_out)
        self._hook(self.model.feature, "feature")
        self.freeze()

    def _run(self, left: Tensor, right: Tensor) -> Tensor:
        return self.model(left, right, iters=self.iters, test_mode=True, optimize_build_volume="pytorch1")

    def _maps(self, batch: int) -> dict[int, list[Tensor]]:
        return {s: [f[:batch]] for s, f in zip(SCALES, self._record["feature"])}
