"""Camera conventions in one place (SPEC section 1 and 4). Pure numpy, float64.

Conventions:
- Camera axes are OpenCV: x right, y down, z forward. ``c2w`` is camera-to-world (what is stored on
  disk), ``viewmat`` is world-to-camera (what the rasteriser takes). Units are metres (world units).
- OpenGL / nerfstudio / Blender cameras have x right, y up, z backward; converting a c2w between the
  two flips the camera's y and z axes (right-multiplication by ``OPENGL_TO_OPENCV``); the world frame
  is left as it is.
- Intrinsics ``K`` are in pixels; pixel (u, v) covers [u, u+1) x [v, v+1), so its centre is
  (u + 0.5, v + 0.5) and a principal point at the image centre is (W/2, H/2).
- ``Trans(v)`` is the 4x4 translation by v; ``T @ Trans(v)`` moves a camera by v expressed in its own
  axes and keeps its orientation (paper appendix B: right camera and targets).
"""

from __future__ import annotations

import math

import numpy as np

# Right-multiplying an OpenGL c2w by this flips the camera's y and z axes: the OpenCV c2w of the same
# camera (and vice versa: the matrix is its own inverse).
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
#: A stereo baseline outside [SHORT_BASELINE, LONG_BASELINE] metres is most likely given in another unit: the
#: cameras of a stereo rig sit millimetres (a phone) to a metre or two (a car, a mount) apart (``baseline_doubt``;
#: ``import multiview`` refuses a baseline beyond LONG_BASELINE).
SHORT_BASELINE, LONG_BASELINE = 0.003, 2.0


def _as_poses(c2w: np.ndarray, name: str) -> np.ndarray:
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: expected [..., 4, 4] matrices, got shape {c2w.shape}")
    return c2w


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """OpenGL c2w [..., 4, 4] (x right, y up, z backward) -> OpenCV c2w [..., 4, 4].

    The camera centre and the world frame are unchanged; the camera's y and z axes flip. The map is an
    involution, so the same function converts OpenCV back to OpenGL.
    """
    return _as_poses(c2w, "c2w") @ OPENGL_TO_OPENCV


def translation(v: np.ndarray) -> np.ndarray:
    """``Trans(v)``: the 4x4 translation by v [..., 3] -> [..., 4, 4]."""
    v = np.asarray(v, dtype=np.float64)
    out = np.broadcast_to(np.eye(4), v.shape[:-1] + (4, 4)).copy()
    out[..., :3, 3] = v
    return out


def rigid_error(c2w: np.ndarray) -> np.ndarray:
    """How far each pose [..., 4, 4] is from a rigid transform (rotation + translation).

    Returns [...]: max(|R^T R - I|, |bottom row - (0,0,0,1)|), or +inf where det(R) <= 0 or any entry is
    not finite. Values near 1e-7 mean rigid up to float32 rounding.
    """
    c2w = _as_poses(c2w, "c2w")
    finite = np.isfinite(c2w).all(axis=(-2, -1))
    safe = np.where(finite[..., None, None], c2w, np.eye(4))
    rot = safe[..., :3, :3]
    ortho = np.abs(np.swapaxes(rot, -1, -2) @ rot - np.eye(3)).max(axis=(-2, -1))
    bottom = np.abs(safe[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    err = np.maximum(ortho, bottom)
    return np.where(finite & (np.linalg.det(rot) > 0), err, np.inf)


def rotation_angle_deg(c2w_a: np.ndarray, c2w_b: np.ndarray) -> np.ndarray:
    """Angle in degrees of the relative rotation R_a^T R_b of poses [..., 4, 4] (broadcasts)."""
    rel = np.swapaxes(np.asarray(c2w_a)[..., :3, :3], -1, -2) @ np.asarray(c2w_b)[..., :3, :3]
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def orthonormalize(c2w: np.ndarray) -> np.ndarray:
    """Project the rotation block of each pose [..., 4, 4] onto SO(3) (nearest in Frobenius norm) and
    set the bottom row to (0, 0, 0, 1). Cleans up rounding in poses read from text files; callers check
    ``rigid_error`` first, so this never hides a pose that is not a rotation."""
    c2w = _as_poses(c2w, "c2w").copy()
    u, _, vt = np.linalg.svd(c2w[..., :3, :3])
    c2w[..., :3, :3] = u @ vt
    c2w[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return c2w


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """OpenCV c2w [..., 4, 4] of a camera at ``eye`` looking at ``target`` (world units).

    ``up`` is the world's up direction; the camera's y axis (down in the image) points away from it.
    The default (0, -1, 0) suits COLMAP / INRIA scenes whose y axis points down; pass (0, 0, 1) for a
    z-up world. Raises ValueError when eye == target or the viewing direction is parallel to ``up``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    forward = target - eye
    norm = np.linalg.norm(forward, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise ValueError("look_at: eye and target coincide")
    z = forward / norm
    x = np.cross(z, up)
    xnorm = np.linalg.norm(x, axis=-1, keepdims=True)
    if np.any(xnorm < 1e-9 * np.linalg.norm(up)):
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x = x / xnorm
    y = np.cross(z, x)
    c2w = np.broadcast_to(np.eye(4), z.shape[:-1] + (4, 4)).copy()
    c2w[..., :3, 0] = x
    c2w[..., :3, 1] = y
    c2w[..., :3, 2] = z
    c2w[..., :3, 3] = eye
    return c2w


def viewmats_from_c2w(c2w: np.ndarray) -> np.ndarray:
    """World-to-camera matrices [..., 4, 4] of rigid c2w poses [..., 4, 4]: [R^T, -R^T t]."""
    c2w = _as_poses(c2w, "c2w")
    rot_t = np.swapaxes(c2w[..., :3, :3], -1, -2)
    out = np.broadcast_to(np.eye(4), c2w.shape).copy()
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ c2w[..., :3, 3:4])[..., 0]
    return out


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Pinhole K [3, 3] in pixels (pixel-centre convention of SPEC section 1)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def scale_intrinsics(K: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """K [..., 3, 3] of an image of ``size`` = (W, H) pixels -> K of the same camera at ``new_size``.

    Pixel (u, v) covers [u, u+1) x [v, v+1), so image coordinates scale by W2/W and H2/H about the
    image corner (0, 0): the first row (fx, skew, cx) scales by W2/W, the second (fy, cy) by H2/H. The
    image centre (W/2, H/2) maps to (W2/2, H2/2), and so does every pixel edge.
    """
    (w, h), (w2, h2) = size, new_size
    if min(w, h, w2, h2) <= 0:
        raise ValueError(f"scale_intrinsics: sizes must be positive, got {size} -> {new_size}")
    out = np.array(K, dtype=np.float64, copy=True)
    out[..., 0, :] *= w2 / w
    out[..., 1, :] *= h2 / h
    return out


def fibonacci_directions(n: int = 10) -> np.ndarray:
    """The n unit target directions u_j [n, 3] of SPEC section 4 (paper appendix B), in the reference
    camera's axes: y = 1 - 2 (j + 0.5) / n, r = sqrt(1 - y^2), phi = j pi (3 - sqrt 5),
    u_j = (r cos phi, y, r sin phi), j = 0..n-1."""
    if n < 1:
        raise ValueError(f"fibonacci_directions: n must be >= 1, got {n}")
    j = np.arange(n, dtype=np.float64)
    y = 1.0 - 2.0 * (j + 0.5) / n
    r = np.sqrt(1.0 - y * y)
    phi = j * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=-1)


def right_camera(c2w_left: np.ndarray, baseline: float) -> np.ndarray:
    """The right camera of a rectified pair: ``T_L Trans(B, 0, 0)`` (SPEC section 4), c2w [..., 4, 4]
    OpenCV, ``baseline`` B in world units (metres), along the left camera's +x (to its right)."""
    return _as_poses(c2w_left, "c2w_left") @ translation(np.array([baseline, 0.0, 0.0]))


def stereo_rig(
    c2w_left: np.ndarray, baseline: float, rho: float, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The right camera and the targets of a reference pose (paper appendix B, SPEC section 4).

    c2w_left [..., 4, 4] (OpenCV), baseline B and radius rho in world units (metres), directions [n, 3]
    in the reference camera's axes. Returns (c2w_right [..., 4, 4], c2w_targets [..., n, 4, 4]) with
    right = T_L Trans(B, 0, 0) and target j = T_L Trans(rho u_j); all keep the reference orientation.
    """
    c2w_left = _as_poses(c2w_left, "c2w_left")
    directions = np.asarray(directions, dtype=np.float64)
    right = right_camera(c2w_left, baseline)
    targets = c2w_left[..., None, :, :] @ translation(rho * directions)
    return right, targets


def orbit_poses(
    center: np.ndarray,
    radius: float,
    n: int,
    elevation_deg: float = 20.0,
    up: np.ndarray = (0.0, -1.0, 0.0),
) -> np.ndarray:
    """n OpenCV c2w poses [n, 4, 4] evenly spaced on a circle around ``center``, looking at it.

    The circle lies ``elevation_deg`` above the plane through ``center`` orthogonal to ``up`` (world
    units; positive elevation looks down on the centre). Frame k sits at azimuth 2 pi k / n, measured
    from the world axis least aligned with ``up`` projected onto that plane.
    """
    if n < 1 or radius <= 0:
        raise ValueError(f"orbit_poses: need n >= 1 and radius > 0, got n={n}, radius={radius}")
    if not -90.0 < elevation_deg < 90.0:
        raise ValueError(f"orbit_poses: elevation_deg must be in (-90, 90), got {elevation_deg}")
    center = np.asarray(center, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    seed_axis = np.eye(3)[np.argmin(np.abs(up))]
    a = seed_axis - up * (seed_axis @ up)
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    az = 2.0 * math.pi * np.arange(n) / n
    el = math.radians(elevation_deg)
    horizontal = np.cos(az)[:, None] * a + np.sin(az)[:, None] * b
    eyes = center + radius * (math.cos(el) * horizontal + math.sin(el) * up)
    return look_at(eyes, np.broadcast_to(center, eyes.shape), up)


def baseline_doubt(baseline: float, where: str, fix_long: str, fix_short: str) -> str | None:
    """The one plausibility check of a stereo baseline (metres), wherever one comes in (``--baseline`` of every
    command, a calibration file, ``--rig-units``): a warning text naming ``where`` and the fix (``fix_long`` for a
    baseline over ``LONG_BASELINE``, e.g. "give --rig-units mm", ``fix_short`` under ``SHORT_BASELINE``), or None."""
    if baseline > LONG_BASELINE:
        return (f"{where}: a baseline of {baseline:.4g} m is long for a stereo rig (up to {LONG_BASELINE:g} m is "
                f"usual): {fix_long}")
    if baseline < SHORT_BASELINE:
        return (f"{where}: a baseline of {baseline:.4g} m is short for a stereo rig ({SHORT_BASELINE * 1000:g} mm "
                f"or more is usual): {fix_short}")
    return None
