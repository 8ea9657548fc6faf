"""View-dependent colour from real spherical harmonics, degrees 0..3 (SPEC section 1, "Colour").

rgb = max(SH(d) + 0.5, 0) with d = normalise(mean - camera centre), in the INRIA/gsplat basis order and
sign convention. The kernel is compiled per degree: a degree-0 scene never reads directions and only
touches its DC coefficient. Culled (camera, Gaussian) pairs (radii (0, 0)) get colour 0 and no work.
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from ._warp import on_device_of, to_wp

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per channel."""
    return (degree + 1) ** 2


@wp.func
def sh_basis_1(d: wp.vec3) -> wp.vec3:
    """Degree-1 basis values (Y_1^-1, Y_1^0, Y_1^1) at unit direction d."""
    return wp.vec3(-SH_C1 * d[1], SH_C1 * d[2], -SH_C1 * d[0])


@functools.cache
def sh_kernel(degree: int):
    """Per (camera, Gaussian) colour kernel, compiled per SH degree."""
    C2_0, C2_1, C2_2, C2_3, C2_4 = SH_C2
    C3_0, C3_1, C3_2, C3_3, C3_4, C3_5, C3_6 = SH_C3

    @wp.kernel(enable_backward=False, module="unique")
    def eval_sh(
        dirs: wp.array2d(dtype=wp.vec3),
        coeffs: wp.array2d(dtype=wp.vec3),
        radii: wp.array2d(dtype=wp.vec2i),
        out_colors: wp.array2d(dtype=wp.vec3),
    ):
        c, g = wp.tid()
        r = radii[c, g]
        if r[0] <= 0 and r[1] <= 0:
            out_colors[c, g] = wp.vec3(0.0, 0.0, 0.0)
            return
        rgb = SH_C0 * coeffs[g, 0]
        if wp.static(degree >= 1):
            v = dirs[c, g]
            n = wp.length(v)
            if n > 0.0:
                v = v / n
            x = v[0]
            y = v[1]
            z = v[2]
            b1 = sh_basis_1(v)
            rgb = rgb + b1[0] * coeffs[g, 1] + b1[1] * coeffs[g, 2] + b1[2] * coeffs[g, 3]
            if wp.static(degree >= 2):
                xx = x * x
                yy = y * y
                zz = z * z
                rgb = (
                    rgb
                    + (C2_0 * x * y) * coeffs[g, 4]
                    + (C2_1 * y * z) * coeffs[g, 5]
                    + (C2_2 * (2.0 * zz - xx - yy)) * coeffs[g, 6]
                    + (C2_3 * x * z) * coeffs[g, 7]
                    + (C2_4 * (xx - yy)) * coeffs[g, 8]
                )
                if wp.static(degree >= 3):
                    rgb = (
                        rgb
                        + (C3_0 * y * (3.0 * xx - yy)) * coeffs[g, 9]
                        + (C3_1 * x * y * z) * coeffs[g, 10]
                        + (C3_2 * y * (4.0 * zz - xx - yy)) * coeffs[g, 11]
                        + (C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)) * coeffs[g, 12]
                        + (C3_4 * x * (4.0 * zz - xx - yy)) * coeffs[g, 13]
                        + (C3_5 * z * (xx - yy)) * coeffs[g, 14]
                        + (C3_6 * x * (xx - 3.0 * yy)) * coeffs[g, 15]
                    )
        out_colors[c, g] = wp.vec3(
            wp.max(rgb[0] + 0.5, 0.0), wp.max(rgb[1] + 0.5, 0.0), wp.max(rgb[2] + 0.5, 0.0)
        )

    return eval_sh


def eval_sh_colors(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """Colours [C, N, 3] from SH ``coeffs`` [N, K, 3] (K >= (degree+1)^2; extra bands are ignored) viewed
    along ``dirs`` [C, N, 3] (mean - camera centre, any length); zero for culled pairs."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be 0..3, got {degree}")
    C, N = radii.shape[:2]
    K = num_sh_bases(degree)
    if coeffs.shape[1] < K:
        raise ValueError(f"colors has {coeffs.shape[1]} SH coefficients per channel, sh_degree={degree} needs {K}")
    out = torch.zeros(C, N, 3, device=coeffs.device, dtype=torch.float32)
    if C == 0 or N == 0:
        return out
    coeffs = coeffs[:, :K].contiguous()
    with on_device_of(coeffs) as device:
        wp.launch(
            sh_kernel(degree),
            dim=(C, N),
            inputs=[to_wp(dirs, wp.vec3), to_wp(coeffs, wp.vec3), to_wp(radii, wp.vec2i)],
            outputs=[to_wp(out, wp.vec3)],
            device=device,
        )
    return out
