"""The foundation-stereo and fast-foundation-stereo adapters against the real upstream code, in one process, in
both orders: build each encoder from the releases of ``scripts/checks/foundation_releases.py``, check that nothing of
either checkout stays in ``sys.modules`` or ``sys.path`` and that logging is as before, then compare what the
adapters return with what the upstream modules compute when called directly (disparity: the model's forward;
image features: ``model.feature``; FoundationStereo's context features: ``model.cnet``; its recurrent features:
the ``net`` list ``model.update_block`` returns on its last call, captured by wrapping its forward). Prints one line
per check and exits 1 on the first mismatch.

    python scripts/checks/foundation_parity.py --fs-repo FS --ffs-repo FFS --releases OUT
"""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from sgmodel.encoders import create_encoder
from sgmodel.encoders.foundation import PAD_MULTIPLE, checkout

NAMES = ("core", "Utils", "depth_anything", "dinov2", "foundation_stereo_ori")


def check(ok: bool, what: str) -> None:
    print(f"{'ok  ' if ok else 'FAIL'} {what}", flush=True)
    if not ok:
        raise SystemExit(1)


def build(name: str, weights: Path, repo: Path, checkouts: tuple[Path, ...]):
    level = logging.root.level
    t0 = time.perf_counter()
    enc = create_encoder(name, weights=str(weights), repo=str(repo))
    modules = [m for m in sys.modules if m.split(".")[0] in NAMES]
    paths = [p for p in sys.path if any(Path(p or ".").resolve().is_relative_to(c.resolve()) for c in checkouts)]
    check(not modules and not paths and logging.root.level == level,
          f"{name} ({weights.parent.name}) built in {time.perf_counter() - t0:.1f} s; no checkout module in "
          f"sys.modules nor folder on sys.path; logging level as before; feature scales {enc.feature_scales}, "
          f"channels {enc.feature_channels}")
    return enc


def pair(h: int, w: int, shift: int = 6) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    tex = F.avg_pool2d(torch.rand(1, 3, h, w + shift, generator=g), 5, 1, 2)
    return tex[..., :w].contiguous(), tex[..., shift:].contiguous()


def padded(x: torch.Tensor) -> torch.Tensor:
    return F.pad(x * 255, (0, -x.shape[-1] % PAD_MULTIPLE, 0, -x.shape[-2] % PAD_MULTIPLE), mode="replicate")


def close(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.shape == b.shape and torch.allclose(a, b, rtol=1e-4, atol=1e-4 * max(1.0, b.abs().max().item()))


def compare(enc, repo: Path, left: torch.Tensor, right: torch.Tensor) -> None:
    """Adapter output against the upstream modules called directly."""
    h, w = left.shape[-2:]
    t0 = time.perf_counter()
    out = enc(left, right)
    seconds = time.perf_counter() - t0
    m, L, R = enc.model, padded(left), padded(right)
    project = "FoundationStereo" if enc.name == "foundation-stereo" else "Fast-FoundationStereo"
    with checkout(repo, enc.name, project, "").active():
        normalize = importlib.import_module("core.foundation_stereo").normalize_image
    hidden = []
    forward = m.update_block.forward
    m.update_block.forward = lambda *a, **k: (lambda r: hidden.append([t.clone() for t in r[0]]) or r)(forward(*a, **k))
    with torch.no_grad():
        kwargs = {} if enc.name == "foundation-stereo" else {"optimize_build_volume": "pytorch1"}
        disparity = m(L, R, iters=enc.iters, test_mode=True, **kwargs)[..., :h, :w]
        image = m.feature(torch.cat([normalize(L), normalize(R)]))
        maps = list(image[0] if enc.name == "foundation-stereo" else image)
        maps = {s: [f[:1]] for s, f in zip((4, 8, 16, 32), maps)}
        if enc.name == "foundation-stereo":
            cnet = m.cnet(normalize(L), vit_feat=image[1][:1], num_layers=m.args.n_gru_layers)
            for j in range(m.args.n_gru_layers):
                maps[4 * 2 ** j] += [torch.relu(cnet[j][1]), hidden[-1][j]]
    del m.update_block.forward
    check(close(out.disparity, disparity), f"{enc.name}: disparity equals the model's forward "
          f"({enc.iters} updates; {w}x{h} in {seconds:.1f} s)")
    check(len(hidden) == enc.iters, f"{enc.name}: update_block called {len(hidden)} times")
    for f, s in zip(out.features, enc.feature_scales):
        ref = torch.cat(maps[s], 1)[..., : math.ceil(h / s), : math.ceil(w / s)]
        check(close(f, ref), f"{enc.name}: features at 1/{s} ({f.shape[1]} channels) equal the upstream modules'")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fs-repo", type=Path, required=True)
    p.add_argument("--ffs-repo", type=Path, required=True)
    p.add_argument("--releases", type=Path, required=True, help="OUT of scripts/checks/foundation_releases.py")
    p.add_argument("--size", default="96x64", help="WxH of the test pair (default 96x64)")
    args = p.parse_args()
    torch.set_grad_enabled(False)
    w, h = (int(v) for v in args.size.split("x"))
    fs = ("foundation-stereo", args.releases / "FoundationStereo/23-51-11/model_best_bp2.pth", args.fs_repo)
    ffs = ("fast-foundation-stereo", args.releases / "Fast-FoundationStereo/23-36-37/model_best_bp2_serialize.pth",
           args.ffs_repo)
    pruned = ("fast-foundation-stereo", args.releases / "Fast-FoundationStereo/pruned/model_best_bp2_serialize.pth",
              args.ffs_repo)
    left, right = pair(h, w)
    for order in ((ffs, fs), (fs, ffs)):
        print(f"-- {order[0][0]} first, then {order[1][0]}, in one process", flush=True)
        built = [(build(*spec, (args.fs_repo, args.ffs_repo)), spec[2]) for spec in order]
        for enc, repo in built:
            compare(enc, repo, left, right)
    enc = build(*pruned, (args.fs_repo, args.ffs_repo))
    check(enc.feature_channels != tuple(enc.model.feature.d_out), f"pruned: measured widths {enc.feature_channels}, "
          f"the code's constants (feature.d_out) {tuple(enc.model.feature.d_out)}; update_block.encoder.convc1 = "
          f"{enc.model.update_block.encoder.convc1}")
    compare(enc, args.ffs_repo, left, right)


if __name__ == "__main__":
    main()
