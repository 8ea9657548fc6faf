"""Projection of 3D Gaussians to screen-space ellipses (SPEC section 2, steps 1-6).

For each camera c and Gaussian g: camera-space mean, EWA covariance through the clamped Jacobian,
low-pass ``eps2d``, antialiasing compensation (a compiled variant, not a run-time branch), conic,
screen-space extent from the 1/255 touch rule, the rectangle of tiles the ellipse can touch, and the box of
pixels it can touch that the compositing kernels vote on (``touch_extent``).
Units: means in world units, screen quantities in pixels, pixel (u, v) centred at (u+0.5, v+0.5).
A culled Gaussian has radii (0, 0), zero effective opacity and touches no tile.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
import warp as wp

from scenesplat_stereo.raster._warp import ALPHA_MIN, launch, to_wp

# SPEC section 2, step 3: tx/z is clamped to 1.3x the half field of view (0.15 W / fx beyond each edge).
JACOBIAN_CLAMP_MARGIN = 0.15
# Extra pixels on each side of the analytic extent so that float32 rounding in the per-pixel touch test can
# never reach a pixel outside the tile rectangle (which would make the image depend on the tile size).
EXTENT_MARGIN_PX = 1e-2


# ``touch_extent`` bounds only conics with (a + c)^2 <= NEAR_CONDITION * (a c - b^2) (condition number up to about
# 1e4): for them float32's sigma is within 0.6% of the exact one (its rounding error is at most a few ulp of
# 0.5 (a dx^2 + c dy^2) + |b dx dy|, which is at most 2 (a + c)^2 / det times sigma), far inside the bound's
# 1% margin in radius (2% in sigma). More elongated conics are never ruled out.
NEAR_CONDITION = 1.0e4


@wp.func
def touch_extent(conic: wp.vec3, opacity: float) -> wp.vec2:
    """Half-widths (rx, ry) in pixels of a box around the mean that holds every pixel centre the splat touches,
    +inf where no bound is given, -inf where it touches nothing. Written per pair by the projection
    (``Projection.touch_extents``) for the compositing kernels' votes (``composite.may_touch_box``).

    A splat touches a pixel where sigma <= ln(255 o) (``composite.touch_alpha``), an ellipse whose bounding box
    has half-widths sqrt(2 t c / det) and sqrt(2 t a / det) (t = ln(255 o), det = a c - b^2: the diagonal of the
    inverse conic). The box is widened by 1% plus 0.01 px and t by 1e-3 for float32 rounding and the fast exp
    and log of the compositing kernels; conics that are not positive definite or too elongated
    (``NEAR_CONDITION``), and NaNs, get no bound. A splat with o < 1/255 touches nothing (o exp(-sigma) <= o
    for sigma >= 0)."""
    if not (opacity >= ALPHA_MIN * 0.999):
        return wp.vec2(-wp.inf, -wp.inf)
    a = conic[0]
    b = conic[1]
    c = conic[2]
    det = a * c - b * b
    if not (a > 0.0 and c > 0.0 and det > 0.0 and (a + c) * (a + c) <= NEAR_CONDITION * det):
        return wp.vec2(wp.inf, wp.inf)
    t = 2.0 * (wp.max(wp.log(opacity / ALPHA_MIN), 0.0) + 1.0e-3)
    return wp.vec2(wp.sqrt(t * c / det) * 1.01 + 0.01, wp.sqrt(t * a / det) * 1.01 + 0.01)


@dataclass
class Projection:
    """Per (camera, Gaussian) screen-space quantities, torch float32/int32 tensors of leading shape [C, N]
    (a batch of scenes: [B * C, N], camera b * C + c with the N Gaussians of scene b)."""

    means2d: torch.Tensor  # [C, N, 2] pixels
    conics: torch.Tensor  # [C, N, 3] (a, b, c) of inverse(Sigma2d + eps2d I) = [[a, b], [b, c]]
    depths: torch.Tensor  # [C, N] camera-space z
    opacities: torch.Tensor  # [C, N] effective opacity o (compensated when antialiased), 0 when culled
    radii: torch.Tensor  # [C, N, 2] int32 extent in pixels per axis, (0, 0) when culled
    tile_rects: torch.Tensor  # [C, N, 4] int32 (tx0, ty0, tx1, ty1) inclusive tile rectangle
    tiles_touched: torch.Tensor  # [C, N] int32 number of tiles in the rectangle, 0 when culled
    touch_extents: torch.Tensor  # [C, N, 2] float32 half-widths (pixels) of ``touch_extent``'s box, -inf when culled


@wp.func
def quat_to_rotation(q: wp.vec4) -> wp.mat33:
    """Rotation matrix of a unit quaternion stored (w, x, y, z)."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def tangent_limits(K: wp.mat33, width: float, height: float) -> wp.vec4:
    """Clamp range of tx/z and ty/z (SPEC step 3): (-low x, high x, -low y, high y) = the field of view
    widened by 0.15 W / fx (0.15 H / fy) on each side, for intrinsics K at width x height pixels."""
    fx = K[0, 0]
    fy = K[1, 1]
    return wp.vec4(
        K[0, 2] / fx + JACOBIAN_CLAMP_MARGIN * width / fx,
        (width - K[0, 2]) / fx + JACOBIAN_CLAMP_MARGIN * width / fx,
        K[1, 2] / fy + JACOBIAN_CLAMP_MARGIN * height / fy,
        (height - K[1, 2]) / fy + JACOBIAN_CLAMP_MARGIN * height / fy,
    )


@wp.func
def view_rotation(V: wp.mat44) -> wp.mat33:
    """The rotation block of a world-to-camera matrix."""
    return wp.mat33(V[0, 0], V[0, 1], V[0, 2], V[1, 0], V[1, 1], V[1, 2], V[2, 0], V[2, 1], V[2, 2])


@wp.func
def clamped_jacobian(p: wp.vec3, K: wp.mat33, width: float, height: float):
    """Rows (J0, J1) of the projection Jacobian at camera-space p with tx/z, ty/z clamped (SPEC step 3)."""
    lim = tangent_limits(K, width, height)
    z = p[2]
    tx = z * wp.clamp(p[0] / z, -lim[0], lim[1])
    ty = z * wp.clamp(p[1] / z, -lim[2], lim[3])
    return (wp.vec3(K[0, 0] / z, 0.0, -K[0, 0] * tx / (z * z)),
            wp.vec3(0.0, K[1, 1] / z, -K[1, 1] * ty / (z * z)))


@wp.func
def screen_covariance(cov_cam: wp.mat33, J0: wp.vec3, J1: wp.vec3) -> wp.vec3:
    """(a, b, d) of Sigma2d = J Sigma_cam J^T = [[a, b], [b, d]] (before the low-pass filter)."""
    return wp.vec3(wp.dot(J0, cov_cam * J0), wp.dot(J0, cov_cam * J1), wp.dot(J1, cov_cam * J1))


@wp.func
def write_culled(
    c: int,
    g: int,
    out_means2d: wp.array2d(dtype=wp.vec2),
    out_conics: wp.array2d(dtype=wp.vec3),
    out_opacities: wp.array2d(dtype=float),
    out_radii: wp.array2d(dtype=wp.vec2i),
    out_rects: wp.array2d(dtype=wp.vec4i),
    out_tiles: wp.array2d(dtype=wp.int32),
    out_extents: wp.array2d(dtype=wp.vec2),
):
    """The outputs of a culled pair: zero mean, conic, opacity and radii, an empty tile rectangle, a touch box
    that holds no pixel."""
    out_means2d[c, g] = wp.vec2(0.0, 0.0)
    out_conics[c, g] = wp.vec3(0.0, 0.0, 0.0)
    out_opacities[c, g] = 0.0
    out_radii[c, g] = wp.vec2i(0, 0)
    out_rects[c, g] = wp.vec4i(0, 0, -1, -1)
    out_tiles[c, g] = 0
    out_extents[c, g] = wp.vec2(-wp.inf, -wp.inf)


@functools.cache
def projection_kernel(antialiased: bool):
    """The projection kernel, compiled per rasterize mode. Thread (c, g) projects Gaussian g of camera c's
    scene: cameras and Gaussians are batches of scenes laid end to end (``cameras_per_scene`` cameras and
    N = out_depths.shape[1] Gaussians each), so camera c sees Gaussians (c / cameras_per_scene) * N + g."""

    @wp.kernel(enable_backward=False, module="unique")
    def project(
        means: wp.array(dtype=wp.vec3),
        quats: wp.array(dtype=wp.vec4),
        scales: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        viewmats: wp.array(dtype=wp.mat44),
        Ks: wp.array(dtype=wp.mat33),
        width: int,
        height: int,
        near_plane: float,
        far_plane: float,
        eps2d: float,
        tile_size: int,
        cameras_per_scene: int,
        out_means2d: wp.array2d(dtype=wp.vec2),
        out_conics: wp.array2d(dtype=wp.vec3),
        out_depths: wp.array2d(dtype=float),
        out_opacities: wp.array2d(dtype=float),
        out_radii: wp.array2d(dtype=wp.vec2i),
        out_rects: wp.array2d(dtype=wp.vec4i),
        out_tiles: wp.array2d(dtype=wp.int32),
        out_extents: wp.array2d(dtype=wp.vec2),
    ):
        c, g = wp.tid()  # every output of the pair is written once: culled at a return, else at the end

        gi = (c / cameras_per_scene) * out_depths.shape[1] + g  # the Gaussian in the flat batch
        V = viewmats[c]
        mean = means[gi]
        # Step 1: camera-space mean; near/far culling (also catches NaN depths: comparisons are false).
        p = wp.vec3(
            V[0, 0] * mean[0] + V[0, 1] * mean[1] + V[0, 2] * mean[2] + V[0, 3],
            V[1, 0] * mean[0] + V[1, 1] * mean[1] + V[1, 2] * mean[2] + V[1, 3],
            V[2, 0] * mean[0] + V[2, 1] * mean[1] + V[2, 2] * mean[2] + V[2, 3],
        )
        out_depths[c, g] = p[2]
        if not (p[2] > near_plane and p[2] < far_plane):
            write_culled(c, g, out_means2d, out_conics, out_opacities, out_radii, out_rects, out_tiles,
                         out_extents)
            return

        # Step 2: world covariance R S S^T R^T, then camera covariance.
        q = quats[gi]
        qn = wp.length(q)
        if not (qn > 0.0):
            write_culled(c, g, out_means2d, out_conics, out_opacities, out_radii, out_rects, out_tiles,
                         out_extents)
            return
        R = quat_to_rotation(q / qn)
        s = scales[gi]
        M = R * wp.diag(s)
        W = view_rotation(V) * M
        cov_cam = W * wp.transpose(W)

        # Step 3: Jacobian at the clamped camera-space position.
        K = Ks[c]
        fx = K[0, 0]
        fy = K[1, 1]
        cx = K[0, 2]
        cy = K[1, 2]
        fw = float(width)
        fh = float(height)
        z = p[2]
        J0, J1 = clamped_jacobian(p, K, fw, fh)
        sig = screen_covariance(cov_cam, J0, J1)
        a = sig[0]
        b = sig[1]
        d = sig[2]

        # Step 4: low-pass filter and antialiasing compensation.
        det_orig = a * d - b * b
        a = a + eps2d
        d = d + eps2d
        det = a * d - b * b
        if not (det > 0.0):
            write_culled(c, g, out_means2d, out_conics, out_opacities, out_radii, out_rects, out_tiles,
                         out_extents)
            return
        o = opacities[gi]
        if wp.static(antialiased):
            o = o * wp.sqrt(wp.max(det_orig / det, 0.0))
        if not (o >= ALPHA_MIN):
            write_culled(c, g, out_means2d, out_conics, out_opacities, out_radii, out_rects, out_tiles,
                         out_extents)
            return

        # Step 5: screen-space mean and conic.
        m2 = wp.vec2(fx * p[0] / z + cx, fy * p[1] / z + cy)
        inv_det = 1.0 / det
        conic = wp.vec3(d * inv_det, -b * inv_det, a * inv_det)

        # Step 6: extent of {sigma <= ln(255 o)}; pixel centres u + 0.5 inside [m - r, m + r].
        level = 2.0 * wp.log(wp.max(o / ALPHA_MIN, 1.0))
        rx = wp.sqrt(level * a) + EXTENT_MARGIN_PX
        ry = wp.sqrt(level * d) + EXTENT_MARGIN_PX
        # Clamp in float before converting to int so that far-away means cannot overflow.
        u0 = wp.clamp(wp.ceil(m2[0] - rx - 0.5), -1.0, fw)
        u1 = wp.clamp(wp.floor(m2[0] + rx - 0.5), -1.0, fw)
        v0 = wp.clamp(wp.ceil(m2[1] - ry - 0.5), -1.0, fh)
        v1 = wp.clamp(wp.floor(m2[1] + ry - 0.5), -1.0, fh)
        if not (u1 >= 0.0 and v1 >= 0.0 and u0 <= fw - 1.0 and v0 <= fh - 1.0 and u0 <= u1 and v0 <= v1):
            write_culled(c, g, out_means2d, out_conics, out_opacities, out_radii, out_rects, out_tiles,
                         out_extents)
            return
        tx0 = int(wp.max(u0, 0.0)) / tile_size
        tx1 = int(wp.min(u1, fw - 1.0)) / tile_size
        ty0 = int(wp.max(v0, 0.0)) / tile_size
        ty1 = int(wp.min(v1, fh - 1.0)) / tile_size

        out_means2d[c, g] = m2
        out_conics[c, g] = conic
        out_opacities[c, g] = o
        out_radii[c, g] = wp.vec2i(int(wp.min(wp.ceil(rx), 1.0e9)), int(wp.min(wp.ceil(ry), 1.0e9)))
        out_rects[c, g] = wp.vec4i(tx0, ty0, tx1, ty1)
        out_tiles[c, g] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
        out_extents[c, g] = touch_extent(conic, o)

    return project


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    antialiased: bool,
    tile_size: int,
    scenes: int = 1,
) -> Projection:
    """Project ``scenes`` scenes of N Gaussians into their C cameras each (float32 tensors on one device;
    see module docstring). Scenes lie end to end: means [scenes * N, 3] (quats, scales, opacities alike),
    viewmats [scenes * C, 4, 4], Ks [scenes * C, 3, 3]; outputs have leading shape [scenes * C, N]."""
    BC, N = viewmats.shape[0], means.shape[0] // max(scenes, 1)  # an empty batch (scenes = 0): N = 0
    f32 = dict(device=means.device, dtype=torch.float32)
    i32 = dict(device=means.device, dtype=torch.int32)
    out = Projection(
        means2d=torch.empty(BC, N, 2, **f32),
        conics=torch.empty(BC, N, 3, **f32),
        depths=torch.empty(BC, N, **f32),
        opacities=torch.empty(BC, N, **f32),
        radii=torch.empty(BC, N, 2, **i32),
        tile_rects=torch.empty(BC, N, 4, **i32),
        tiles_touched=torch.empty(BC, N, **i32),
        touch_extents=torch.empty(BC, N, 2, **f32),
    )
    if BC == 0 or N == 0:
        return out
    launch(
        projection_kernel(bool(antialiased)), (BC, N),
        [
            to_wp(means, wp.vec3), to_wp(quats, wp.vec4), to_wp(scales, wp.vec3), to_wp(opacities),
            to_wp(viewmats, wp.mat44), to_wp(Ks, wp.mat33), int(width), int(height), float(near_plane),
            float(far_plane), float(eps2d), int(tile_size), BC // scenes,
            to_wp(out.means2d, wp.vec2), to_wp(out.conics, wp.vec3), to_wp(out.depths), to_wp(out.opacities),
            to_wp(out.radii, wp.vec2i), to_wp(out.tile_rects, wp.vec4i), to_wp(out.tiles_touched),
            to_wp(out.touch_extents, wp.vec2),
        ],
        means,
    )
    return out
