"""View-dependent colour from real spherical harmonics, degrees 0..3 (SPEC section 1, "Colour").

rgb = max(SH(d) + 0.5, 0) with d = normalise(mean - camera centre), in the INRIA/gsplat basis order and
sign convention; the camera centre -R^T t of a rigid world-to-camera matrix [R t] is taken in the kernel
(``view_direction``), so no [C, N, 3] direction tensor is built. The kernel is compiled per degree: a
degree-0 scene never reads means or cameras and only touches its DC coefficient. Culled (camera, Gaussian)
pairs (radii (0, 0)) get colour 0 and no work. The basis and its constants are the scene's
(``scenesplat_stereo.scene.harmonics``, evaluated in PyTorch by the float64 reference); this is its Warp kernel.
"""

# No ``from __future__ import annotations``: Warp evaluates the annotations of the per-degree basis
# function, whose return type is created in its factory.
import functools

import torch
import warp as wp

from scenesplat_stereo.raster._warp import launch, to_wp, vector_type
from scenesplat_stereo.scene.harmonics import SH_C0, SH_C1, SH_C2, SH_C3


def num_sh_bases(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per channel."""
    return (degree + 1) ** 2


@functools.cache
def sh_basis_func(degree: int):
    """A Warp function: the K = (degree+1)^2 real SH basis values Y_k(v) at unit direction v (a vector
    of length K; degree 0 never reads v)."""
    vecK = vector_type(num_sh_bases(degree))
    C2_0, C2_1, C2_2, C2_3, C2_4 = SH_C2
    C3_0, C3_1, C3_2, C3_3, C3_4, C3_5, C3_6 = SH_C3

    @wp.func
    def sh_basis(v: wp.vec3) -> vecK:
        b = vecK()
        b[0] = SH_C0
        if wp.static(degree >= 1):
            x = v[0]
            y = v[1]
            z = v[2]
            b[1] = -SH_C1 * y
            b[2] = SH_C1 * z
            b[3] = -SH_C1 * x
            if wp.static(degree >= 2):
                xx = x * x
                yy = y * y
                zz = z * z
                b[4] = C2_0 * x * y
                b[5] = C2_1 * y * z
                b[6] = C2_2 * (2.0 * zz - xx - yy)
                b[7] = C2_3 * x * z
                b[8] = C2_4 * (xx - yy)
                if wp.static(degree >= 3):
                    b[9] = C3_0 * y * (3.0 * xx - yy)
                    b[10] = C3_1 * x * y * z
                    b[11] = C3_2 * y * (4.0 * zz - xx - yy)
                    b[12] = C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
                    b[13] = C3_4 * x * (4.0 * zz - xx - yy)
                    b[14] = C3_5 * z * (xx - yy)
                    b[15] = C3_6 * x * (xx - 3.0 * yy)
        return b

    return sh_basis


@wp.func
def view_direction(mean: wp.vec3, V: wp.mat44) -> wp.vec3:
    """mean - camera centre (world units) for the world-to-camera matrix V = [R t; 0 1]: the centre is
    -R^T t, so the direction is mean + R^T t."""
    return wp.vec3(
        mean[0] + V[0, 0] * V[0, 3] + V[1, 0] * V[1, 3] + V[2, 0] * V[2, 3],
        mean[1] + V[0, 1] * V[0, 3] + V[1, 1] * V[1, 3] + V[2, 1] * V[2, 3],
        mean[2] + V[0, 2] * V[0, 3] + V[1, 2] * V[1, 3] + V[2, 2] * V[2, 3],
    )


@functools.cache
def sh_kernel(degree: int):
    """Per (camera, Gaussian) colour kernel, compiled per SH degree. For a batch of scenes laid end to end,
    camera c sees Gaussian (c / cameras_per_scene) * N + g (its mean and coefficients)."""
    sh_basis = sh_basis_func(degree)
    K = num_sh_bases(degree)

    @wp.kernel(enable_backward=False, module="unique")
    def eval_sh(
        means: wp.array(dtype=wp.vec3),
        viewmats: wp.array(dtype=wp.mat44),
        coeffs: wp.array2d(dtype=wp.vec3),
        radii: wp.array2d(dtype=wp.vec2i),
        cameras_per_scene: int,
        out_colors: wp.array2d(dtype=wp.vec3),
    ):
        c, g = wp.tid()
        gi = (c / cameras_per_scene) * radii.shape[1] + g
        r = radii[c, g]
        if r[0] <= 0 and r[1] <= 0:
            out_colors[c, g] = wp.vec3(0.0, 0.0, 0.0)
            return
        v = wp.vec3(0.0, 0.0, 0.0)
        if wp.static(degree >= 1):
            d = view_direction(means[gi], viewmats[c])
            n = wp.length(d)
            if n > 0.0:
                v = d / n
        basis = sh_basis(v)
        rgb = wp.vec3(0.0, 0.0, 0.0)
        for k in range(K):
            rgb = rgb + basis[k] * coeffs[gi, k]
        out_colors[c, g] = wp.vec3(
            wp.max(rgb[0] + 0.5, 0.0), wp.max(rgb[1] + 0.5, 0.0), wp.max(rgb[2] + 0.5, 0.0)
        )

    return eval_sh


def eval_sh_colors(degree: int, means: torch.Tensor, viewmats: torch.Tensor, coeffs: torch.Tensor,
                   radii: torch.Tensor, scenes: int = 1) -> torch.Tensor:
    """Colours [C, N, 3] of Gaussians at ``means`` [N, 3] with SH ``coeffs`` [N, K, 3] (K >= (degree+1)^2;
    extra bands are ignored) seen from the cameras of world-to-camera ``viewmats`` [C, 4, 4]; zero for
    culled pairs (``radii`` [C, N, 2] of the projection). A batch of ``scenes`` scenes lies end to end:
    means [scenes * N, 3], coeffs [scenes * N, K, 3], viewmats [scenes * C, 4, 4], radii [scenes * C, N, 2]."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be 0..3, got {degree}")
    C, N = radii.shape[:2]
    K = num_sh_bases(degree)
    if coeffs.shape[1] < K:
        raise ValueError(f"colors has {coeffs.shape[1]} SH coefficients per channel, sh_degree={degree} needs {K}")
    out = torch.empty(C, N, 3, device=coeffs.device, dtype=torch.float32)  # every pair is written
    if C == 0 or N == 0:
        return out
    launch(sh_kernel(degree), (C, N),
           [to_wp(means, wp.vec3), to_wp(viewmats, wp.mat44), to_wp(coeffs, wp.vec3), to_wp(radii, wp.vec2i),
            C // scenes, to_wp(out, wp.vec3)],
           coeffs)
    return out
