"""Where the rasteriser's forward time goes on the GPU: each stage timed alone (median of 20 runs,
synchronised), for the headline workloads of ``bench render``. Used by scripts/gpu/bench.sh (profile)."""

from __future__ import annotations

import statistics
import time

import torch

from scenesplat_stereo.bench.render import GUITAR, Setting, guitar_scene, identity_camera, random_scene
from scenesplat_stereo.raster import rasterization
from scenesplat_stereo.raster.binning import bin_gaussians
from scenesplat_stereo.raster.composite import composite_forward
from scenesplat_stereo.raster.projection import project_gaussians
from scenesplat_stereo.raster.sh import eval_sh_colors


def sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def timed(fn, repeats: int = 20) -> float:
    for _ in range(3):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def backward_rows(scene: dict, viewmats, Ks, s: Setting, proj, colors, bins) -> dict[str, float]:
    """Backward stages alone (cotangents of ones), and forward + backward of the whole call."""
    from scenesplat_stereo.raster.composite_backward import composite_backward
    from scenesplat_stereo.raster.projection_backward import project_gaussians_backward

    W, H, ts = s.width, s.height, s.tile_size
    render, alphas, last_ids = composite_forward(proj.means2d, proj.conics, colors, proj.opacities, bins, W, H, ts,
                                                 0.999, proj.touch_extents)
    v_render, v_alphas = torch.ones_like(render), torch.ones_like(alphas)
    m, q, sc, o = (scene[k] for k in ("means", "quats", "scales", "opacities"))
    ones = lambda t: torch.ones_like(t)  # noqa: E731

    def full():
        leaves = {k: v.detach().requires_grad_(True) for k, v in scene.items()}
        out = rasterization(*(leaves[k] for k in ("means", "quats", "scales", "opacities", "colors")), viewmats, Ks,
                            W, H, sh_degree=s.sh_degree, rasterize_mode="antialiased", max_alpha=0.999)[0]
        out.sum().backward()

    return {
        "composite backward": timed(lambda: composite_backward(
            proj.means2d, proj.conics, colors, proj.opacities, bins, W, H, ts, 0.999, alphas, last_ids, v_render,
            v_alphas)),
        "projection backward": timed(lambda: project_gaussians_backward(
            m, q, sc, o, viewmats, Ks, W, H, 0.3, True, proj.radii, ones(proj.means2d), ones(proj.conics),
            ones(proj.depths), ones(proj.opacities))),
        "forward + backward (all)": timed(full),
    }


def profile(name: str, scene: dict, viewmats, Ks, s: Setting, backward: bool = False) -> None:
    """Time each forward stage alone on one batch of cameras, and the whole rasterization call."""
    W, H, ts = s.width, s.height, s.tile_size
    m, q, sc, o, col = (scene[k] for k in ("means", "quats", "scales", "opacities", "colors"))
    proj = project_gaussians(m, q, sc, o, viewmats, Ks, W, H, 0.01, 1e10, 0.3, True, ts)
    colors = eval_sh_colors(s.sh_degree, m, viewmats, col, proj.radii)
    bins = bin_gaussians(proj, W, H, ts)
    rows = {
        "project": timed(lambda: project_gaussians(m, q, sc, o, viewmats, Ks, W, H, 0.01, 1e10, 0.3, True, ts)),
        "sh colours": timed(lambda: eval_sh_colors(s.sh_degree, m, viewmats, col, proj.radii)),
        "bin (scan, keys, sort, ranges)": timed(lambda: bin_gaussians(proj, W, H, ts)),
        "composite": timed(lambda: composite_forward(proj.means2d, proj.conics, colors, proj.opacities, bins, W,
                                                     H, ts, 0.999, proj.touch_extents)),
        "rasterization (all)": timed(lambda: rasterization(m, q, sc, o, col, viewmats, Ks, W, H,
                                                           sh_degree=s.sh_degree, rasterize_mode="antialiased",
                                                           max_alpha=0.999)),
    }
    if backward:
        rows.update(backward_rows(scene, viewmats, Ks, s, proj, colors, bins))
    visible = int((proj.radii[..., 0] > 0).sum())
    print(f"\n{name}: {visible:,} visible, {bins.flatten_ids.numel():,} tile intersections")
    for k, v in rows.items():
        print(f"  {k:32s} {v:7.3f} ms")


def build_batch(width: int, height: int, cameras: int = 48):
    """The dataset build's call: 4 pairs x 12 cameras around one reference (10 cm apart) in a 1M room."""
    from scenesplat_stereo.bench.build import synthetic_teacher
    from scenesplat_stereo.scene.cameras import viewmats_from_c2w

    teacher, gaussians = synthetic_teacher(1_000_000, 3, cameras, (width, height), "cuda")
    viewmats = torch.tensor(viewmats_from_c2w(teacher.c2w), dtype=torch.float32, device="cuda")
    Ks = torch.tensor(teacher.Ks, dtype=torch.float32, device="cuda")
    return gaussians, viewmats, Ks


def main() -> None:
    s = Setting(n=1_000_000, width=1280, height=720)
    profile("random 1M SH3 1280x720", random_scene(s.n, 3, "cuda"), *identity_camera(1280, 720, "cuda"), s,
            backward=True)
    for w, h in ((616, 456), (1752, 1168)):
        profile(f"build batch: 48 cameras {w}x{h}, 1M-Gaussian room, SH3", *build_batch(w, h),
                Setting(n=1_000_000, width=w, height=h, sh_degree=3))
    if GUITAR.exists():
        g, v, K = guitar_scene("cuda", 1280, 720)
        profile("guitar 1280x720", g, v, K, Setting(n=g["means"].shape[0], width=1280, height=720, sh_degree=0),
                backward=True)


if __name__ == "__main__":
    main()
