"""CUDA-vs-CPU parity of the Warp rasteriser (one kernel source, two devices), run by scripts/gpu_bench.sh.

Renders random scenes in every render mode, rasterize mode and SH degree on both devices and reports the
largest differences of images, alphas and (when the backward pass is available) gradients. Exits non-zero
when a difference exceeds float32 round-off tolerances.
"""

from __future__ import annotations

import sys

import torch

from scenesplat_stereo.bench.render import identity_camera, random_scene
from scenesplat_stereo.raster import RENDER_MODES, rasterization


def render(scene, device, **kw):
    leaves = {k: v.to(device).detach().requires_grad_(True) for k, v in scene.items()}
    viewmats, Ks = identity_camera(96, 64, device)
    out, alpha, _ = rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                  leaves["colors"], viewmats.repeat(2, 1, 1), Ks.repeat(2, 1, 1), 96, 64, **kw)
    grads = {}
    try:
        (out.square().sum() + alpha.sum()).backward()
        grads = {k: v.grad.cpu() for k, v in leaves.items()}
    except NotImplementedError:
        pass
    return out.detach().cpu(), alpha.detach().cpu(), grads


def main() -> int:
    worst = 0.0
    for sh in range(4):
        scene = random_scene(4000, sh, "cpu", seed=sh)
        for mode in RENDER_MODES:
            for rm in ("classic", "antialiased"):
                kw = dict(sh_degree=sh, render_mode=mode, rasterize_mode=rm)
                a, b = render(scene, "cpu", **kw), render(scene, "cuda", **kw)
                scale = max(1.0, float(a[0].abs().max()))
                d_img = float((a[0] - b[0]).abs().max()) / scale
                d_alpha = float((a[1] - b[1]).abs().max())
                d_grad = max((float((a[2][k] - b[2][k]).abs().max() / (a[2][k].abs().max() + 1e-12))
                              for k in a[2]), default=float("nan"))
                worst = max(worst, d_img, d_alpha)
                print(f"sh={sh} {mode:7s} {rm:11s} max|img| rel {d_img:.2e}  max|alpha| {d_alpha:.2e}  "
                      f"max grad rel {d_grad:.2e}")
    print(f"worst image/alpha difference CPU vs CUDA: {worst:.2e}")
    return 0 if worst < 1e-4 else 1


if __name__ == "__main__":
    sys.exit(main())
