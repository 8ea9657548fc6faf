"""Reverse of the view-dependent SH colours (SPEC section 1, "Colour"): rgb = max(SH(d) + 0.5, 0) with
d = normalise(dir), dir = mean - camera centre (world units), real SH in the INRIA/gsplat basis of sh.py.

Gradients: d rgb / d coeff_k = Y_k(d) per channel (zero in channels where the clamp at 0 binds);
d rgb / d d = sum_k coeff_k dY_k/dd, taken through the normalisation, d dir = (g - d (d . g)) / |dir|
(a zero direction, a Gaussian at the camera centre, gets a zero gradient), and d dir / d mean = I. One
thread per Gaussian walks the cameras of its scene in order, sums its coefficient and mean gradients in
registers and writes each once (no zero-fill first), without atomics (reproducible). Compiled per degree:
degree 0 never reads means or cameras and has no mean gradient. Culled (camera, Gaussian) pairs contribute
nothing.
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from scenesplat_stereo.raster._warp import launch, to_wp, vector_type
from scenesplat_stereo.raster.sh import SH_C1, SH_C2, SH_C3, num_sh_bases, sh_basis_func, view_direction


@functools.cache
def sh_backward_kernel(degree: int):
    """Per-Gaussian SH backward kernel, compiled per SH degree. Thread (b, g) owns Gaussian b * N + g of
    the flat batch and walks its scene's cameras b * C .. b * C + C - 1 (C = ``cameras_per_scene``)."""
    C2_0, C2_1, C2_2, C2_3, C2_4 = SH_C2
    C3_0, C3_1, C3_2, C3_3, C3_4, C3_5, C3_6 = SH_C3
    sh_basis = sh_basis_func(degree)
    K = num_sh_bases(degree)
    vecK = vector_type(K)

    @wp.kernel(enable_backward=False, module="unique")
    def sh_backward(
        means: wp.array(dtype=wp.vec3),
        viewmats: wp.array(dtype=wp.mat44),
        coeffs: wp.array2d(dtype=wp.vec3),
        radii: wp.array2d(dtype=wp.vec2i),
        v_colors: wp.array2d(dtype=wp.vec3),
        cameras_per_scene: int,
        out_v_coeffs: wp.array2d(dtype=wp.vec3),
        out_v_means: wp.array(dtype=wp.vec3),
    ):
        b, g = wp.tid()
        gi = b * radii.shape[1] + g
        # Sums over the cameras, per coefficient and channel (red, green, blue), and of the mean's gradient.
        sum_r = vecK()
        sum_g = vecK()
        sum_b = vecK()
        v_mean = wp.vec3(0.0, 0.0, 0.0)
        for c in range(b * cameras_per_scene, (b + 1) * cameras_per_scene):
            r = radii[c, g]
            if r[0] <= 0 and r[1] <= 0:
                continue
            # Forward colour (before the clamp) to find the channels where max(., 0) passes gradient.
            v = wp.vec3(0.0, 0.0, 0.0)
            n = float(0.0)
            if wp.static(degree >= 1):
                v = view_direction(means[gi], viewmats[c])
                n = wp.length(v)
                if n > 0.0:
                    v = v / n
            basis = sh_basis(v)
            rgb = wp.vec3(0.0, 0.0, 0.0)
            for k in range(K):
                rgb = rgb + basis[k] * coeffs[gi, k]
            vc = v_colors[c, g]
            vc = wp.vec3(
                wp.where(rgb[0] + 0.5 >= 0.0, vc[0], 0.0),
                wp.where(rgb[1] + 0.5 >= 0.0, vc[1], 0.0),
                wp.where(rgb[2] + 0.5 >= 0.0, vc[2], 0.0),
            )
            for k in range(K):
                sum_r[k] = sum_r[k] + basis[k] * vc[0]
                sum_g[k] = sum_g[k] + basis[k] * vc[1]
                sum_b[k] = sum_b[k] + basis[k] * vc[2]
            if wp.static(degree >= 1):
                # d rgb / d v, contracted with vc: sum_k (coeff_k . vc) grad Y_k(v)
                w1 = wp.dot(coeffs[gi, 1], vc)
                w2 = wp.dot(coeffs[gi, 2], vc)
                w3 = wp.dot(coeffs[gi, 3], vc)
                v_v = SH_C1 * wp.vec3(-w3, -w1, w2)
                if wp.static(degree >= 2):
                    x = v[0]
                    y = v[1]
                    z = v[2]
                    xx = x * x
                    yy = y * y
                    zz = z * z
                    w4 = wp.dot(coeffs[gi, 4], vc)
                    w5 = wp.dot(coeffs[gi, 5], vc)
                    w6 = wp.dot(coeffs[gi, 6], vc)
                    w7 = wp.dot(coeffs[gi, 7], vc)
                    w8 = wp.dot(coeffs[gi, 8], vc)
                    v_v += w4 * C2_0 * wp.vec3(y, x, 0.0)
                    v_v += w5 * C2_1 * wp.vec3(0.0, z, y)
                    v_v += w6 * C2_2 * wp.vec3(-2.0 * x, -2.0 * y, 4.0 * z)
                    v_v += w7 * C2_3 * wp.vec3(z, 0.0, x)
                    v_v += w8 * C2_4 * wp.vec3(2.0 * x, -2.0 * y, 0.0)
                    if wp.static(degree >= 3):
                        w9 = wp.dot(coeffs[gi, 9], vc)
                        w10 = wp.dot(coeffs[gi, 10], vc)
                        w11 = wp.dot(coeffs[gi, 11], vc)
                        w12 = wp.dot(coeffs[gi, 12], vc)
                        w13 = wp.dot(coeffs[gi, 13], vc)
                        w14 = wp.dot(coeffs[gi, 14], vc)
                        w15 = wp.dot(coeffs[gi, 15], vc)
                        v_v += w9 * C3_0 * wp.vec3(6.0 * x * y, 3.0 * (xx - yy), 0.0)
                        v_v += w10 * C3_1 * wp.vec3(y * z, x * z, x * y)
                        v_v += w11 * C3_2 * wp.vec3(-2.0 * x * y, 4.0 * zz - xx - 3.0 * yy, 8.0 * y * z)
                        v_v += w12 * C3_3 * wp.vec3(-6.0 * x * z, -6.0 * y * z, 6.0 * zz - 3.0 * xx - 3.0 * yy)
                        v_v += w13 * C3_4 * wp.vec3(4.0 * zz - 3.0 * xx - yy, -2.0 * x * y, 8.0 * x * z)
                        v_v += w14 * C3_5 * wp.vec3(2.0 * x * z, -2.0 * y * z, xx - yy)
                        v_v += w15 * C3_6 * wp.vec3(3.0 * (xx - yy), -6.0 * x * y, 0.0)
                if n > 0.0:
                    v_mean += (v_v - v * wp.dot(v, v_v)) / n
        for k in range(K):
            out_v_coeffs[gi, k] = wp.vec3(sum_r[k], sum_g[k], sum_b[k])
        for k in range(K, out_v_coeffs.shape[1]):  # bands beyond the degree
            out_v_coeffs[gi, k] = wp.vec3(0.0, 0.0, 0.0)
        if wp.static(degree >= 1):
            out_v_means[gi] = v_mean

    return sh_backward


def eval_sh_colors_backward(
    degree: int, means: torch.Tensor, viewmats: torch.Tensor, coeffs: torch.Tensor, radii: torch.Tensor,
    v_colors: torch.Tensor, scenes: int = 1,
) -> tuple[torch.Tensor | None, torch.Tensor]:
    """Gradients (means [N,3], None for degree 0; coeffs [N,K,3]) of ``sh.eval_sh_colors`` from the
    cotangent ``v_colors`` [C,N,3]; bands beyond ``degree`` get zero gradient. For a batch of ``scenes``
    scenes laid end to end, C and every N are scenes times larger (see ``eval_sh_colors``)."""
    C, N = radii.shape[:2]
    f32 = dict(device=coeffs.device, dtype=torch.float32)
    if C == 0 or N == 0:
        return (torch.zeros(means.shape, **f32) if degree > 0 else None), torch.zeros(coeffs.shape, **f32)
    v_coeffs = torch.empty(coeffs.shape, **f32)  # every entry is written
    v_means = torch.empty(means.shape, **f32) if degree > 0 else None
    launch(sh_backward_kernel(degree), (scenes, N),
           [to_wp(means, wp.vec3), to_wp(viewmats, wp.mat44), to_wp(coeffs, wp.vec3), to_wp(radii, wp.vec2i),
            to_wp(v_colors, wp.vec3), C // scenes, to_wp(v_coeffs, wp.vec3),
            to_wp(v_means if v_means is not None else means, wp.vec3)],
           coeffs)
    return v_means, v_coeffs
