"""Teacher scenes: ``GaussianScene`` and its ``.ply`` reading and writing. Pure numpy.

Conventions (SPEC section 1): world units as in the file (metres for SceneSplat teachers); quaternions
wxyz, unit norm; scales linear; opacities in [0, 1]; SH coefficients ``[N, K, 3]`` with K = (d+1)^2,
``sh[:, 0]`` the DC term.

This module owns the INRIA layout (3DGS trainer, gsplat, nerfstudio, SuperSplat export) on the PLY container
of ``scenesplat_stereo.scene.ply`` (header, elements): element ``vertex`` with properties read by name, in any order and of any
numeric type; ``x y z``, ``f_dc_0..2``, optional ``f_rest_*`` (0, 9, 24 or 45 of them, channel-major),
``opacity`` (a logit), ``scale_0..2`` (natural logs), ``rot_0..3`` (wxyz, any norm); ``nx ny nz`` and any
other property are ignored. ascii, binary_little_endian, binary_big_endian. ``load_ply`` also reads the
PlayCanvas / SuperSplat compressed layout (an element named ``chunk``), whose reader and writer live in
``scenesplat_stereo.scene.compressed_ply``.

Rows with non-finite values, zero-norm quaternions or scales that are zero (below the smallest normal
float32) or infinite in float32 are dropped and counted in one warning (``PlyRepairWarning``), or raise
with ``strict=True``.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scenesplat_stereo.common.files import atomic_write_bytes
from scenesplat_stereo.scene.compressed_ply import decode_compressed
from scenesplat_stereo.scene.ply import PlyError, PlyHeader, PlyRepairWarning, columns, read_elements, read_ply_header

#: Opacities are clipped to [eps, 1 - eps] before the logit in ``save_ply`` so that 0 and 1 stay finite.
OPACITY_EPS = 1e-7
#: Quaternions whose norm is within this of 1 are kept bit-exact on load (unit within float32 rounding).
QUAT_UNIT_ATOL = 2.0**-20
#: ``GaussianScene`` rejects quaternions whose norm is further than this from 1.
QUAT_VALIDATE_ATOL = 1e-4
#: The per-Gaussian arrays of a ``GaussianScene``, in its order.
ARRAYS = ("means", "quats", "scales", "opacities", "sh")


@dataclass(eq=False)
class GaussianScene:
    """A 3D Gaussian scene in memory (numpy float32, row i is Gaussian i).

    means [N,3] world units; quats [N,4] wxyz unit norm; scales [N,3] linear, > 0; opacities [N] in
    [0, 1]; sh [N,K,3] real SH coefficients, K = (sh_degree+1)^2, colour = max(SH(d) + 0.5, 0).
    """

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    sh_degree: int

    def __post_init__(self) -> None:
        if isinstance(self.sh_degree, bool) or not isinstance(self.sh_degree, (int, np.integer)) \
                or not 0 <= self.sh_degree <= 3:
            raise ValueError(f"GaussianScene.sh_degree must be an int in 0..3, got {self.sh_degree!r}")
        self.sh_degree = int(self.sh_degree)
        n = self.means.shape[0] if isinstance(self.means, np.ndarray) and self.means.ndim == 2 else None
        k = (self.sh_degree + 1) ** 2
        for name, shape in (("means", (n, 3)), ("quats", (n, 4)), ("scales", (n, 3)),
                            ("opacities", (n,)), ("sh", (n, k, 3))):
            a = getattr(self, name)
            if not isinstance(a, np.ndarray) or a.dtype != np.float32:
                raise ValueError(f"GaussianScene.{name} must be a numpy float32 array, got "
                                 f"{type(a).__name__} {getattr(a, 'dtype', '')} (use .astype(np.float32))")
            if n is None or a.shape != shape:
                want = "[N, 3]" if n is None else str(list(shape))
                raise ValueError(f"GaussianScene.{name} must have shape {want} (sh_degree "
                                 f"{self.sh_degree}), got {list(a.shape)}")
            if not np.isfinite(a).all():  # rows counted only when the cheap whole-array test fails
                bad = int((~np.isfinite(a)).reshape(n, int(np.prod(shape[1:]))).any(1).sum())
                raise ValueError(f"GaussianScene.{name} has {bad} rows with non-finite values")
        q = self.quats.astype(np.float64)
        checks = (  # each the rows that fail it
            ("quats", np.abs(np.sqrt(np.einsum("ij,ij->i", q, q)) - 1.0) > QUAT_VALIDATE_ATOL,
             f"not unit norm (±{QUAT_VALIDATE_ATOL})"),
            ("scales", (self.scales <= 0).any(1), "not > 0"),
            ("opacities", (self.opacities < 0) | (self.opacities > 1), "outside [0, 1]"),
        )
        for name, bad, what in checks:
            if bad.any():
                raise ValueError(f"GaussianScene.{name}: {int(bad.sum())} rows {what}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_gaussians(self) -> int:
        """N, the number of Gaussians."""
        return len(self)

    def subset(self, mask_or_index: Any) -> GaussianScene:
        """A new scene (copied arrays) of the rows selected by a bool mask [N], integer indices or a slice."""
        sel = mask_or_index
        if not isinstance(sel, slice):
            sel = np.asarray(sel)
            if sel.dtype == bool:
                if sel.shape != (len(self),):
                    raise ValueError(f"subset: bool mask must have shape [{len(self)}], "
                                     f"got {list(sel.shape)}")
            elif sel.size == 0:
                sel = sel.astype(np.int64)
            elif not np.issubdtype(sel.dtype, np.integer) or sel.ndim != 1:
                raise ValueError(f"subset: expected a bool mask, 1-D integer indices or a slice, got "
                                 f"{sel.dtype} {list(sel.shape)}")
        return GaussianScene(self.means[sel].copy(), self.quats[sel].copy(), self.scales[sel].copy(),
                             self.opacities[sel].copy(), self.sh[sel].copy(), self.sh_degree)

    def to_torch(self, device: Any = "cpu") -> dict[str, Any]:
        """float32 torch tensors keyed by gsplat's ``rasterization`` argument names.

        ``colors`` is the SH tensor [N,K,3]; pass ``sh_degree=scene.sh_degree`` alongside.
        """
        import torch

        arrays = {"means": self.means, "quats": self.quats, "scales": self.scales,
                  "opacities": self.opacities, "colors": self.sh}
        return {k: torch.from_numpy(np.ascontiguousarray(v)).to(device) for k, v in arrays.items()}

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min [3], max [3]) of the means, world units."""
        self._require_nonempty("bounds")
        return self.means.min(0), self.means.max(0)

    def median(self) -> np.ndarray:
        """Per-axis median [3] of the means, world units."""
        self._require_nonempty("median")
        return np.median(self.means, axis=0).astype(np.float32)

    def _require_nonempty(self, what: str) -> None:
        if len(self) == 0:
            raise ValueError(f"GaussianScene.{what}() of an empty scene")


def content_sh_degree(sh: np.ndarray) -> int:
    """The smallest SH degree that holds every non-zero coefficient of sh [N, K, 3] (0 when the bands above
    the DC term are all zero, e.g. plain-colour Gaussians). Takes a numpy array or a torch tensor (which
    is reduced where it lives: on a GPU only K booleans come back)."""
    used = (sh != 0).any(-1).any(0).tolist()  # [K]: is coefficient k non-zero anywhere
    return math.isqrt(max((k for k, u in enumerate(used) if u), default=0))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return np.exp(-np.logaddexp(0.0, -x))


def _decode_inria(header: PlyHeader) -> tuple[np.ndarray, ...]:
    path = header.path
    v = read_elements(header, {"vertex"})["vertex"]
    n_rest = 3 * ((header.sh_degree + 1) ** 2 - 1)
    rest_names = [f"f_rest_{i}" for i in range(n_rest)]
    present = set(p for p in v.dtype.names or () if p.startswith("f_rest_"))
    if present != set(rest_names):
        raise PlyError(f"{path}: f_rest_* properties must be f_rest_0..f_rest_{n_rest - 1}; unexpected "
                       f"{sorted(present - set(rest_names))}, missing {sorted(set(rest_names) - present)}")
    names = ["x", "y", "z", "rot_0", "rot_1", "rot_2", "rot_3", "scale_0", "scale_1", "scale_2", "opacity"]
    cols = columns(path, v, "vertex", names)
    columns(path, v[:0], "vertex", ["f_dc_0", "f_dc_1", "f_dc_2"])  # checks presence only
    n, k = len(v), (header.sh_degree + 1) ** 2
    sh = np.empty((n, k, 3), dtype=np.float32)  # float32 straight away: SH is most of a large scene
    with np.errstate(all="ignore"):  # doubles beyond the float32 range become inf: non-finite, dropped
        for c in range(3):
            sh[:, 0, c] = v[f"f_dc_{c}"]
            for j in range(1, k):  # channel-major: f_rest index c (K-1) + j-1
                sh[:, j, c] = v[rest_names[c * (k - 1) + j - 1]]
        opacities = _sigmoid(cols[:, 10])
    finite = np.isfinite(cols).all(1) & np.isfinite(sh).all((1, 2))
    return cols[:, 0:3], cols[:, 3:7], cols[:, 7:10], opacities, sh, finite


def _assemble(header: PlyHeader, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray,
              opacities: np.ndarray, sh: np.ndarray, finite: np.ndarray, strict: bool) -> GaussianScene:
    """Drop (or, strict, refuse) bad rows, normalise quaternions, and build the float32 scene."""
    norm = np.linalg.norm(np.where(finite[:, None], quats, 0.0), axis=1)
    zero_quat = finite & (norm == 0)
    with np.errstate(all="ignore"):
        scales = np.exp(np.where(finite[:, None], log_scales, 0.0)).astype(np.float32)
    # Scales below the smallest normal float32 (subnormal or 0) square to 0 in a covariance: zero.
    bad_scale = finite & ~zero_quat & ((scales < np.finfo(np.float32).tiny) | ~np.isfinite(scales)).any(1)
    counts = {"non-finite values": int((~finite).sum()), "zero-norm quaternions": int(zero_quat.sum()),
              "zero or non-finite scales (after exp)": int(bad_scale.sum())}
    keep = finite & ~zero_quat & ~bad_scale
    if not keep.all():
        msg = (f"{header.path}: {int((~keep).sum())} of {len(keep)} Gaussians have bad rows: "
               + ", ".join(f"{v} with {k}" for k, v in counts.items()))
        if strict:
            raise PlyError(msg + " (strict=True)")
        warnings.warn(msg + "; those rows were dropped", PlyRepairWarning, stacklevel=3)
    sel = slice(None) if keep.all() else keep  # no copy of the (large) SH array when nothing is dropped
    q, nq = quats[sel], norm[sel, None]
    q = np.where(np.abs(nq - 1.0) <= QUAT_UNIT_ATOL, q, q / np.where(nq == 0, 1.0, nq))
    return GaussianScene(means[sel].astype(np.float32), q.astype(np.float32), scales[sel],
                         opacities[sel].astype(np.float32), sh[sel], header.sh_degree)


def load_ply(path: str | os.PathLike, strict: bool = False) -> GaussianScene:
    """Read a Gaussian ``.ply`` (INRIA or PlayCanvas compressed layout, detected) into a ``GaussianScene``.

    Bad files raise ``PlyError`` naming the file and field. Rows with non-finite values, zero-norm
    quaternions or scales that are 0 (below the smallest normal) or inf in float32 are dropped with one
    ``PlyRepairWarning`` giving the counts per reason, or raise ``PlyError`` when ``strict``. Quaternions
    already unit within ``QUAT_UNIT_ATOL`` are kept bit-exact; others are divided by their norm (float64).
    """
    header = read_ply_header(path)
    if header.layout == "compressed":
        return _assemble(header, *decode_compressed(header), strict=strict)
    return _assemble(header, *_decode_inria(header), strict=strict)


def inria_property_names(sh_degree: int) -> list[str]:
    """The standard INRIA vertex property order written by ``save_ply``."""
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def save_ply(scene: GaussianScene, path: str | os.PathLike, durable: bool = True) -> Path:
    """Write ``scene`` in the INRIA layout (binary little-endian float32, standard property order).

    ``opacity`` = logit(clip(o, OPACITY_EPS, 1 - OPACITY_EPS)), ``scale_*`` = ln(s), both computed in
    float64 and stored as float32; ``nx ny nz`` = 0; ``f_rest`` channel-major. The vertex table is built
    in one float32 [N, P] array (row i = vertex i, the file's bytes) and written with the header through
    ``files.atomic_write_bytes`` (temp file, fsync'd unless ``durable`` is False, ``os.replace``). Returns
    the path.
    """
    path = Path(path)
    n, k = len(scene), (scene.sh_degree + 1) ** 2
    names = inria_property_names(scene.sh_degree)
    table = np.empty((n, len(names)), dtype="<f4")
    rest = 9 + 3 * (k - 1)  # columns: xyz 0-2, normals 3-5, f_dc 6-8, f_rest 9.., opacity, scales, rot
    table[:, 0:3] = scene.means
    table[:, 3:6] = 0.0
    table[:, 6:9] = scene.sh[:, 0, :]
    channel_major = table[:, 9:rest]
    channel_major.shape = (n, 3, k - 1)  # a view (setting .shape never copies): one strided pass below
    channel_major[:] = scene.sh[:, 1:, :].transpose(0, 2, 1)
    o = np.clip(scene.opacities.astype(np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    table[:, rest] = np.log(o / (1.0 - o))
    table[:, rest + 1:rest + 4] = np.log(scene.scales.astype(np.float64))
    table[:, rest + 4:rest + 8] = scene.quats
    head = "\n".join(["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
                     + [f"property float {p}" for p in names] + ["end_header\n"])
    atomic_write_bytes(path, [head.encode("ascii"), table], durable=durable)
    return path


def decoded_scene(source: str | os.PathLike, error: type[ValueError], means: np.ndarray, quats: np.ndarray,
                  log_scales: np.ndarray, opacities: np.ndarray, sh: np.ndarray, sh_degree: int) -> GaussianScene:
    """The ``GaussianScene`` of arrays a quantised-format reader decoded (float64 or float32): means [N, 3],
    quats [N, 4] wxyz (any non-zero norm; divided by it), log_scales [N, 3] natural logs, opacities [N] in
    [0, 1], sh [N, K, 3]. A value that is not finite, a zero-norm quaternion or a scale that is 0 or inf in
    float32 raises ``error`` naming ``source`` and the field: the formats that come here are written by tools
    that never store such rows, so one is a broken file, not a row to repair (``load_ply`` repairs)."""
    fields = {"means": means, "quats": quats, "log_scales": log_scales, "opacities": opacities, "sh": sh}
    for name, a in fields.items():
        bad = ~np.isfinite(a).reshape(len(a), -1).all(1)
        if bad.any():
            raise error(f"{source}: {name}: {int(bad.sum())} of {len(a)} Gaussians decode to non-finite values "
                        f"(the first is Gaussian {int(np.argmax(bad))})")
    norm = np.linalg.norm(quats.astype(np.float64), axis=1, keepdims=True)
    if (norm == 0).any():
        raise error(f"{source}: quats: {int((norm == 0).sum())} Gaussians have a zero-norm rotation")
    with np.errstate(over="ignore", under="ignore"):
        scales = np.exp(log_scales.astype(np.float64)).astype(np.float32)
    bad = ((scales < np.finfo(np.float32).tiny) | ~np.isfinite(scales)).any(1)
    if bad.any():
        raise error(f"{source}: scales: {int(bad.sum())} Gaussians have a scale that is 0 or inf in float32 "
                    f"(log-scale {float(log_scales[bad][0].min()):g}..{float(log_scales[bad][0].max()):g})")
    return GaussianScene(means.astype(np.float32), (quats / norm).astype(np.float32), scales,
                         np.clip(opacities, 0.0, 1.0).astype(np.float32), sh.astype(np.float32), sh_degree)
