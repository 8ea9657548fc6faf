"""The real spherical-harmonics basis of a scene's view-dependent colour (SPEC section 1, "Colour"), degrees 0..3.

rgb = max(sum_k sh[k] Y_k(d) + 0.5, 0) with d the unit direction from the camera centre to the Gaussian, in the
INRIA / gsplat basis order and sign convention. The one place of the constants and the basis: the rasteriser's
kernels (``scenesplat_stereo.raster.sh``), its float64 reference and the scene transform
(``scenesplat_stereo.scene.transform``) all evaluate this.
"""

from __future__ import annotations

from typing import Any

import numpy as np

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


def sh_basis(degree: int, dirs: Any) -> Any:
    """The real SH basis [..., (degree+1)^2] at unit directions ``dirs`` [..., 3], in the INRIA / gsplat order and
    signs; ``dirs`` a numpy array or a torch tensor (the result is of the same kind and dtype: float64 for the
    reference and for rotating SH coefficients)."""
    if isinstance(dirs, np.ndarray):
        xp = np
    else:
        import torch
        xp = torch
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [xp.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return xp.stack(out, -1)
