"""CUDA parity of the Warp rasteriser against the float64 reference (scenesplat_stereo/raster/reference.py), for
scripts/gpu/bench.sh: the CPU path is covered by the test suite, this covers the CUDA build of the same
kernel source.

Renders random scenes in every render mode, rasterize mode and SH degree with our CUDA kernels and with the
float64 torch reference (on the CPU, float parameters rounded to float32 as the tests do), and reports PSNR,
the largest alpha difference and the relative gradient error per parameter group. Exits non-zero past the
test thresholds (PSNR 50 dB, alpha 1e-3, gradients 1e-3), and when any parameter group has no gradient.
"""

from __future__ import annotations

import sys

import torch

from scenesplat_stereo.bench.render import identity_camera, psnr, random_scene
from scenesplat_stereo.raster import RENDER_MODES, rasterization
from scenesplat_stereo.raster.reference import as_renderer_sees, reference_rasterization


def render(scene, device, dtype, **kw):
    impl, kw = (rasterization, kw) if dtype == torch.float32 else (reference_rasterization, as_renderer_sees(kw))
    leaves = {k: v.to(device, dtype).detach().requires_grad_(True) for k, v in scene.items()}
    viewmats, Ks = identity_camera(96, 64, device)
    viewmats = viewmats.to(dtype) @ torch.tensor([[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]],
                                                 dtype=dtype, device=device)
    out, alpha, _ = impl(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                         leaves["colors"], torch.cat([torch.eye(4, dtype=dtype, device=device)[None], viewmats]),
                         Ks.to(dtype).repeat(2, 1, 1), 96, 64, **kw)
    weights = torch.linspace(0.5, 1.5, out.numel(), dtype=dtype, device=device).reshape(out.shape)
    ((out * weights).sum() + alpha.sum()).backward()
    grads = {k: v.grad.cpu().double() for k, v in leaves.items() if v.grad is not None}  # missing: a failure
    return out.detach().cpu().double(), alpha.detach().cpu().double(), grads


def main() -> int:
    failures = 0
    for sh in range(4):
        scene = random_scene(1500, sh, "cpu", seed=sh)
        for mode in RENDER_MODES:
            for rm in ("classic", "antialiased"):
                kw = dict(sh_degree=sh, render_mode=mode, rasterize_mode=rm)
                ours, ref = render(scene, "cuda", torch.float32, **kw), render(scene, "cpu", torch.float64, **kw)
                scale = float(ref[0].abs().max().clamp_min(1.0))
                p = psnr(ours[0] / scale, ref[0] / scale)
                d_alpha = float((ours[1] - ref[1]).abs().max())
                missing = sorted(set(ref[2]) - set(ours[2]))  # a group without gradient fails, never passes
                d_grad = max((float((ours[2][k] - ref[2][k]).norm() / (ref[2][k].norm() + 1e-12))
                              for k in ref[2] if k in ours[2]), default=0.0)
                bad = p < 50 or d_alpha > 1e-3 or d_grad > 1e-3 or bool(missing) or not ref[2]
                failures += bad
                print(f"sh={sh} {mode:7s} {rm:11s} PSNR {p:6.1f} dB  max|alpha| {d_alpha:.1e}  "
                      f"grad rel err {d_grad:.1e}"
                      f"{'  missing gradients: ' + ', '.join(missing) if missing else ''}{'  FAIL' if bad else ''}")
    print(f"CUDA vs float64 reference: {failures} failing configurations")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
