"""Parity of our LPIPS-VGG (sgmodel.metrics.lpips) with the ``lpips`` package, for a machine where torchvision and
``lpips`` import (the GPU machine; ``lpips`` is pure Python: carry its wheel, ``lpips==0.1.4``, and install
it with ``pip install --no-deps --target DIR`` or point ``--lpips-src`` at the unpacked wheel).

Both sides get the same weights: the LPIPS v0.1 linear layers of the installed ``lpips`` package, and
torchvision's ImageNet VGG16 when ``vgg16-397923af.pth`` is in torch's hub cache (or ``--vgg PATH``), else
random VGG16 weights (torchvision's own initialisation, seeded) saved in torchvision's format and loaded
by both. Compares per-image values, per-pixel maps (``spatial=True``) and input gradients on random images
of several sizes; prints the largest differences and exits 1 when one exceeds 1e-5 relative to the
largest reference magnitude. TF32 is off so that both sides compute in true float32.

    python scripts/checks/gpu_lpips_check.py [--device cuda] [--vgg PATH] [--lpips-src DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

TOLERANCE = 1e-5  # relative to the largest |reference| of each compared quantity


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--vgg", help="torchvision-format VGG16 weights (default: torch's hub cache, else random)")
    ap.add_argument("--lpips-src", help="folder that holds the `lpips` package (an unpacked wheel)")
    args = ap.parse_args()
    if args.lpips_src:
        sys.path.insert(0, args.lpips_src)
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False

    import lpips as lpips_pkg
    import torchvision

    from sgmodel.metrics.lpips import create_lpips, find_vgg16_weights

    tv_vgg16 = torchvision.models.vgg16  # before lpips's reference to it is replaced below
    vgg_file = find_vgg16_weights(args.vgg)
    tmp = tempfile.TemporaryDirectory(prefix="lpips-check-")
    if vgg_file is None:
        torch.manual_seed(0)
        vgg_file = Path(tmp.name) / "vgg16-random.pth"
        torch.save(tv_vgg16(weights=None).state_dict(), vgg_file)
        print(f"VGG16: random weights (torchvision init, seed 0) saved in torchvision format to {vgg_file}")
    else:
        print(f"VGG16: {vgg_file}")
    vgg_state = torch.load(vgg_file, map_location="cpu", weights_only=True)

    def vgg16_with_our_weights(*_args, **_kwargs):
        """lpips 0.1.4 calls tv.vgg16(pretrained=...): hand it a VGG16 holding exactly the file's weights."""
        model = tv_vgg16(weights=None)
        model.load_state_dict(vgg_state, strict=True)
        return model

    lpips_pkg.pretrained_networks.tv.vgg16 = vgg16_with_our_weights
    lin_file = Path(lpips_pkg.__file__).parent / "weights" / "v0.1" / "vgg.pth"
    theirs = lpips_pkg.LPIPS(net="vgg", version="0.1", verbose=False).to(args.device).eval()
    ours = create_lpips(vgg_file, lin_file, device=args.device)
    print(f"lpips {getattr(lpips_pkg, '__version__', '?')} from {lpips_pkg.__file__}; linear layers {lin_file}; "
          f"torchvision {torchvision.__version__}; torch {torch.__version__}; device {args.device}")

    g = torch.Generator().manual_seed(1)
    worst = 0.0
    for shape in [(4, 3, 64, 64), (2, 3, 97, 131), (1, 3, 256, 256)]:
        a = torch.rand(shape, generator=g).to(args.device)
        b = (a.cpu() + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1).to(args.device)
        rows = {}
        theirs.spatial = False
        ref = theirs(a, b, normalize=True).reshape(-1)
        rows["value"] = (ours(a, b), ref)
        theirs.spatial = True
        rows["map"] = (ours.per_pixel(a, b), theirs(a, b, normalize=True))
        theirs.spatial = False
        ref_pm = theirs(2 * a - 1, 2 * b - 1).reshape(-1)
        rows["value [-1,1]"] = (ours(2 * a - 1, 2 * b - 1, zero_one=False), ref_pm)
        xa = a.clone().requires_grad_(True)
        xb = a.clone().requires_grad_(True)
        ours(xa, b).sum().backward()
        theirs(xb, b, normalize=True).sum().backward()
        rows["input grad"] = (xa.grad, xb.grad)
        for name, (got, want) in rows.items():
            err = (got.detach() - want.detach()).abs().max().item()
            rel = err / max(want.detach().abs().max().item(), 1e-30)
            worst = max(worst, rel)
            print(f"{str(shape):>18} {name:>13}: max |ours - lpips| = {err:.3e} (relative {rel:.3e})")
    tmp.cleanup()
    ok = worst <= TOLERANCE
    print(f"{'PASS' if ok else 'FAIL'}: worst relative difference {worst:.3e} (tolerance {TOLERANCE:.0e})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
