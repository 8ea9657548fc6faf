"""Reverse of the projection of 3D Gaussians (SPEC section 2, steps 1-5): screen-space gradients to
means, quaternions (wxyz, normalised inside), linear scales and opacities.

One thread per Gaussian walks the C cameras of its scene in order and sums their contributions locally (no atomics,
so the result is reproducible bit for bit). Per camera, with p = R_view mean + t_view (OpenCV camera,
z forward), Sigma2d = J Sigma_cam J^T = [[a, b], [b, d]], Sigma2d' = Sigma2d + eps2d I and
conic = inverse(Sigma2d') = (d', -b, a') / det':

- conic -> (a, b, d): d conic / d Sigma2d' by the quotient rule (b is the shared off-diagonal entry);
- antialiased: o = opacity sqrt(det / det'), which also feeds (a, b, d) and the opacity;
- (a, b, d) -> Sigma_cam = J^T G J and J = 2 G J Sigma_cam, with G = [[g_a, g_b / 2], [g_b / 2, g_d]];
- J -> p: J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]] with tx = z clamp(p.x / z). Where the
  clamp binds tx / z is a constant: no gradient to p.x and d(-fx tx / z^2)/dz = fx (tx/z) / z^2;
- mean2d = (fx p.x/z + cx, fy p.y/z + cy) and depth = p.z -> p -> mean (R_view^T);
- Sigma_cam -> Sigma_world = R_view^T (.) R_view, summed over cameras, then Sigma = M M^T with
  M = R(q) diag(s): d M = 2 G_world M, d s_j = column j of R . column j of d M, d R = d M diag(s);
  d q from d R(q) and finally through q / |q| (the radial part of the gradient is removed).

Culled (camera, Gaussian) pairs (radii (0, 0)) contribute exactly nothing; a Gaussian culled in every
camera gets exact zeros.
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from scenesplat_stereo.raster._warp import launch, to_wp
from scenesplat_stereo.raster.projection import (clamped_jacobian, quat_to_rotation, screen_covariance, tangent_limits,
                                                 view_rotation)


@wp.func
def rotation_vjp(q: wp.vec4, v_R: wp.mat33) -> wp.vec4:
    """Gradient with respect to a unit wxyz quaternion q of <v_R, R(q)> (R as in quat_to_rotation)."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return 2.0 * wp.vec4(
        x * (v_R[2, 1] - v_R[1, 2]) + y * (v_R[0, 2] - v_R[2, 0]) + z * (v_R[1, 0] - v_R[0, 1]),
        -2.0 * x * (v_R[1, 1] + v_R[2, 2]) + y * (v_R[0, 1] + v_R[1, 0]) + z * (v_R[0, 2] + v_R[2, 0])
        + w * (v_R[2, 1] - v_R[1, 2]),
        x * (v_R[0, 1] + v_R[1, 0]) - 2.0 * y * (v_R[0, 0] + v_R[2, 2]) + z * (v_R[1, 2] + v_R[2, 1])
        + w * (v_R[0, 2] - v_R[2, 0]),
        x * (v_R[0, 2] + v_R[2, 0]) + y * (v_R[1, 2] + v_R[2, 1]) - 2.0 * z * (v_R[0, 0] + v_R[1, 1])
        + w * (v_R[1, 0] - v_R[0, 1]),
    )


@functools.cache
def projection_backward_kernel(antialiased: bool):
    """The projection backward kernel, compiled per rasterize mode. Thread (scene, g) owns Gaussian scene * N + g
    of the flat batch and walks cameras scene * C .. scene * C + C - 1 (C = ``cameras_per_scene``)."""

    @wp.kernel(enable_backward=False, module="unique")
    def project_backward(
        means: wp.array(dtype=wp.vec3),
        quats: wp.array(dtype=wp.vec4),
        scales: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        viewmats: wp.array(dtype=wp.mat44),
        Ks: wp.array(dtype=wp.mat33),
        width: int,
        height: int,
        eps2d: float,
        cameras_per_scene: int,
        radii: wp.array2d(dtype=wp.vec2i),
        v_means2d: wp.array2d(dtype=wp.vec2),
        v_conics: wp.array2d(dtype=wp.vec3),
        v_depths: wp.array2d(dtype=float),
        v_opacities_eff: wp.array2d(dtype=float),
        out_v_means: wp.array(dtype=wp.vec3),
        out_v_quats: wp.array(dtype=wp.vec4),
        out_v_scales: wp.array(dtype=wp.vec3),
        out_v_opacities: wp.array(dtype=float),
    ):
        scene, g = wp.tid()
        gi = scene * radii.shape[1] + g  # the Gaussian in the flat batch
        v_mean = wp.vec3(0.0, 0.0, 0.0)
        v_opacity = float(0.0)
        v_cov = wp.mat33(0.0)  # d loss / d Sigma (world), symmetric
        q = quats[gi]
        qn = wp.length(q)
        # A zero quaternion is culled in every camera by the forward pass (nothing to differentiate).
        if not (qn > 0.0):
            out_v_means[gi] = v_mean
            out_v_quats[gi] = wp.vec4(0.0, 0.0, 0.0, 0.0)
            out_v_scales[gi] = wp.vec3(0.0, 0.0, 0.0)
            out_v_opacities[gi] = 0.0
            return
        qhat = q / qn
        R = quat_to_rotation(qhat)
        s = scales[gi]
        M = R * wp.diag(s)
        mean = means[gi]
        opacity = opacities[gi]
        fw = float(width)
        fh = float(height)
        for c in range(scene * cameras_per_scene, (scene + 1) * cameras_per_scene):
            r = radii[c, g]
            v_m2 = v_means2d[c, g]
            vc = v_conics[c, g]
            v_z = v_depths[c, g]
            v_o = v_opacities_eff[c, g]
            # Culled, or never composited: nothing to add (and no 0 * inf from a degenerate covariance).
            if (r[0] <= 0 and r[1] <= 0) or (v_m2[0] == 0.0 and v_m2[1] == 0.0 and vc[0] == 0.0 and vc[1] == 0.0
                                             and vc[2] == 0.0 and v_z == 0.0 and v_o == 0.0):
                continue
            V = viewmats[c]
            Rv = view_rotation(V)
            p = Rv * mean + wp.vec3(V[0, 3], V[1, 3], V[2, 3])
            W = Rv * M
            cov_cam = W * wp.transpose(W)
            K = Ks[c]
            fx = K[0, 0]
            fy = K[1, 1]
            lim = tangent_limits(K, fw, fh)
            lim_x_neg = lim[0]
            lim_x_pos = lim[1]
            lim_y_neg = lim[2]
            lim_y_pos = lim[3]
            z = p[2]
            ux = p[0] / z
            uy = p[1] / z
            tx = z * wp.clamp(ux, -lim_x_neg, lim_x_pos)
            ty = z * wp.clamp(uy, -lim_y_neg, lim_y_pos)
            J0, J1 = clamped_jacobian(p, K, fw, fh)
            sig = screen_covariance(cov_cam, J0, J1)
            a = sig[0]
            b = sig[1]
            d = sig[2]
            det_orig = a * d - b * b
            ap = a + eps2d
            dp = d + eps2d
            det = ap * dp - b * b

            # conic = (dp, -b, ap) / det  ->  (a, b, d)
            inv_det2 = 1.0 / (det * det)
            v_a = (-dp * dp * vc[0] + b * dp * vc[1] - b * b * vc[2]) * inv_det2
            v_d = (-b * b * vc[0] + b * ap * vc[1] - ap * ap * vc[2]) * inv_det2
            v_b = (2.0 * b * dp * vc[0] - (ap * dp + b * b) * vc[1] + 2.0 * b * ap * vc[2]) * inv_det2
            if wp.static(antialiased):
                comp = wp.sqrt(wp.max(det_orig / det, 0.0))
                v_opacity += v_o * comp
                if comp > 0.0:
                    # d comp = d(det_orig / det) / (2 comp)
                    k = v_o * opacity * 0.5 / comp * inv_det2
                    v_a += k * (d * det - det_orig * dp)
                    v_d += k * (a * det - det_orig * ap)
                    v_b += k * (-2.0 * b * (det - det_orig))
            else:
                v_opacity += v_o

            # (a, b, d) = J Sigma_cam J^T  ->  Sigma_cam, J
            v_cov_cam = (
                v_a * wp.outer(J0, J0) + (0.5 * v_b) * (wp.outer(J0, J1) + wp.outer(J1, J0))
                + v_d * wp.outer(J1, J1)
            )
            cJ0 = cov_cam * J0
            cJ1 = cov_cam * J1
            v_J0 = 2.0 * v_a * cJ0 + v_b * cJ1
            v_J1 = 2.0 * v_d * cJ1 + v_b * cJ0

            # J, mean2d, depth  ->  p
            iz = 1.0 / z
            iz2 = iz * iz
            v_p = wp.vec3(
                fx * iz * v_m2[0],
                fy * iz * v_m2[1],
                -(fx * p[0] * v_m2[0] + fy * p[1] * v_m2[1]) * iz2 + v_z
                - fx * iz2 * v_J0[0] - fy * iz2 * v_J1[1],
            )
            if ux < -lim_x_neg or ux > lim_x_pos:
                v_p[2] += fx * tx * iz2 * iz * v_J0[2]
            else:
                v_p[0] += -fx * iz2 * v_J0[2]
                v_p[2] += 2.0 * fx * tx * iz2 * iz * v_J0[2]
            if uy < -lim_y_neg or uy > lim_y_pos:
                v_p[2] += fy * ty * iz2 * iz * v_J1[2]
            else:
                v_p[1] += -fy * iz2 * v_J1[2]
                v_p[2] += 2.0 * fy * ty * iz2 * iz * v_J1[2]
            v_mean += wp.transpose(Rv) * v_p
            v_cov += wp.transpose(Rv) * v_cov_cam * Rv

        # Sigma = M M^T, M = R(qhat) diag(s)
        v_M = 2.0 * v_cov * M
        v_R = v_M * wp.diag(s)
        v_s = wp.vec3(
            R[0, 0] * v_M[0, 0] + R[1, 0] * v_M[1, 0] + R[2, 0] * v_M[2, 0],
            R[0, 1] * v_M[0, 1] + R[1, 1] * v_M[1, 1] + R[2, 1] * v_M[2, 1],
            R[0, 2] * v_M[0, 2] + R[1, 2] * v_M[1, 2] + R[2, 2] * v_M[2, 2],
        )
        v_qhat = rotation_vjp(qhat, v_R)
        out_v_means[gi] = v_mean
        out_v_quats[gi] = (v_qhat - qhat * wp.dot(qhat, v_qhat)) / qn
        out_v_scales[gi] = v_s
        out_v_opacities[gi] = v_opacity

    return project_backward


def project_gaussians_backward(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    eps2d: float,
    antialiased: bool,
    radii: torch.Tensor,
    v_means2d: torch.Tensor,
    v_conics: torch.Tensor,
    v_depths: torch.Tensor,
    v_opacities: torch.Tensor,
    scenes: int = 1,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gradients (means [N,3], quats [N,4], scales [N,3], opacities [N]) summed over the C cameras, from
    the cotangents of ``project_gaussians``' outputs means2d [C,N,2], conics [C,N,3], depths [C,N] and
    effective opacities [C,N]; ``radii`` [C,N,2] is its output (culled pairs are skipped). For a batch of
    ``scenes`` scenes laid end to end (see ``project_gaussians``) every leading N is scenes * N and every
    C is scenes * C; each Gaussian sums over its own scene's cameras."""
    BN = means.shape[0]
    f32 = dict(device=means.device, dtype=torch.float32)
    new = torch.zeros if BN == 0 or viewmats.shape[0] == 0 else torch.empty  # the kernel writes every Gaussian
    out = (new(BN, 3, **f32), new(BN, 4, **f32), new(BN, 3, **f32), new(BN, **f32))
    if BN == 0 or viewmats.shape[0] == 0:
        return out
    launch(
        projection_backward_kernel(bool(antialiased)), (scenes, BN // scenes),
        [
            to_wp(means, wp.vec3), to_wp(quats, wp.vec4), to_wp(scales, wp.vec3), to_wp(opacities),
            to_wp(viewmats, wp.mat44), to_wp(Ks, wp.mat33), int(width), int(height), float(eps2d),
            viewmats.shape[0] // scenes, to_wp(radii, wp.vec2i), to_wp(v_means2d, wp.vec2), to_wp(v_conics, wp.vec3),
            to_wp(v_depths), to_wp(v_opacities),
            to_wp(out[0], wp.vec3), to_wp(out[1], wp.vec4), to_wp(out[2], wp.vec3), to_wp(out[3]),
        ],
        means,
    )
    return out
