"""Small independent PLY writer and float64 reference decode for the .ply tests (written from SPEC
section 1 and the compressed-PLY format description, never from scenesplat_stereo.scene.gaussians)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.gaussians import GaussianScene

C0 = 0.28209479177387814
EPS32 = 2.0**-24  # unit roundoff of float32 (half an ulp at 1)
NPTYPE = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
          "float": "f4", "double": "f8"}

# ---------------------------------------------------------------- an independent PLY writer

def write_ply(path: Path, elements: list, fmt: str = "binary_little_endian", trailing: bytes = b"") -> Path:
    """elements: [(name, [(prop, ply_type, values[N]), ...]), ...] written in that order."""
    lines = ["ply", f"format {fmt} 1.0", "comment written by test_gaussians"]
    body = []
    for name, props in elements:
        n = len(props[0][2])
        lines.append(f"element {name} {n}")
        lines += [f"property {t} {p}" for p, t, _ in props]
        if fmt == "ascii":
            cols = [[repr(float(x)) if NPTYPE[t][0] == "f" else str(int(x)) for x in v] for _, t, v in props]
            body += [(" ".join(row) + "\n").encode() for row in zip(*cols)]
        else:
            bo = "<" if fmt == "binary_little_endian" else ">"
            arr = np.empty(n, dtype=[(p, bo + NPTYPE[t]) for p, t, _ in props])
            for p, _, v in props:
                arr[p] = v
            body.append(arr.tobytes())
    lines.append("end_header\n")
    path.write_bytes("\n".join(lines).encode() + b"".join(body) + trailing)
    return path


def inria_names(degree: int, normals: bool = True) -> list[str]:
    """The INRIA property order (3DGS `construct_list_of_attributes`, gsplat and nerfstudio exports)."""
    rest = [f"f_rest_{i}" for i in range(3 * ((degree + 1) ** 2 - 1))]
    return (["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"] + rest
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def random_raw(rng: np.random.Generator, n: int, degree: int) -> dict[str, np.ndarray]:
    """File-space values (logit opacity, log scales, non-unit wxyz), float32-representable."""
    raw = {}
    for name in inria_names(degree):
        if name == "opacity":
            v = rng.normal(0, 3, n)
        elif name.startswith("scale_"):
            v = rng.uniform(-7, 1, n)
        elif name.startswith("f_rest_"):
            v = rng.normal(0, 0.3, n)
        else:
            v = rng.normal(0, 1.5, n)
        raw[name] = v.astype(np.float32).astype(np.float64)
    return raw


def inria_props(raw: dict, order: list[str], types: dict | None = None) -> list:
    return [("vertex", [(p, (types or {}).get(p, "float"), raw[p]) for p in order])]


def reference_decode(raw: dict, degree: int) -> dict[str, np.ndarray]:
    """SPEC section 1, in float64 with explicit loops for the channel-major f_rest."""
    n, k = len(raw["x"]), (degree + 1) ** 2
    q = np.stack([raw[f"rot_{i}"] for i in range(4)], 1)
    sh = np.zeros((n, k, 3))
    for c in range(3):
        sh[:, 0, c] = raw[f"f_dc_{c}"]
        for j in range(1, k):
            sh[:, j, c] = raw[f"f_rest_{c * (k - 1) + j - 1}"]
    return {"means": np.stack([raw["x"], raw["y"], raw["z"]], 1),
            "quats": q / np.linalg.norm(q, axis=1, keepdims=True),
            "scales": np.exp(np.stack([raw[f"scale_{i}"] for i in range(3)], 1)),
            "opacities": 1.0 / (1.0 + np.exp(-raw["opacity"])), "sh": sh}


def assert_matches_reference(scene: GaussianScene, ref: dict) -> None:
    """Loaded float32 values equal the float64 reference rounded to float32 (within its rounding)."""
    assert scene.means.dtype == np.float32 and len(scene) == len(ref["means"])
    np.testing.assert_array_equal(scene.means, ref["means"].astype(np.float32))
    np.testing.assert_array_equal(scene.sh, ref["sh"].astype(np.float32))
    np.testing.assert_allclose(scene.quats, ref["quats"], rtol=0, atol=4 * EPS32)
    np.testing.assert_allclose(scene.opacities, ref["opacities"], rtol=0, atol=2 * EPS32)
    np.testing.assert_allclose(scene.scales, ref["scales"], rtol=2 * EPS32, atol=0)


def random_scene(rng: np.random.Generator, n: int, degree: int) -> GaussianScene:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    o = rng.uniform(0, 1, n)
    o[: min(n, 2)] = [0.0, 1.0][: min(n, 2)]  # the extremes must survive the logit
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return GaussianScene(f32(rng.normal(0, 3, (n, 3))), f32(q), f32(np.exp(rng.uniform(-9, 4, (n, 3)))),
                         f32(o), f32(rng.normal(0, 0.5, (n, (degree + 1) ** 2, 3))), degree)
