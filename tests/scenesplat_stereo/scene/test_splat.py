"""scenesplat_stereo.scene.splat: the reader against a float64 decode written from the format description (32-byte
records, as splat-transform 3.7.0 reads them), against splat-transform's decode of the real captures
(tests/data/captures, scripts/inputs/capture_samples.py), and its refusals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from tests.scenesplat_stereo.scene.test_sog import CAPTURES, DATA, assert_matches, check_against_sample

from scenesplat_stereo.scene.scene_files import load_scene, scene_info
from scenesplat_stereo.scene.splat import load_splat


def records(rng: np.random.Generator, n: int) -> bytes:
    """n random records: float32 xyz, float32 linear scales, uint8 rgba, uint8 wxyz (c * 128 + 128)."""
    out = bytearray()
    for _ in range(n):
        out += np.array(rng.normal(0, 2, 3), "<f4").tobytes() + np.array(np.exp(rng.uniform(-6, 1, 3)), "<f4").tobytes()
        out += bytes(rng.integers(0, 256, 8).tolist())
    return bytes(out)


def reference_decode(data: bytes) -> tuple[np.ndarray, ...]:
    n = len(data) // 32
    means, quats, log_scales, opacities, sh = (np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3)), np.zeros(n),
                                               np.zeros((n, 1, 3)))
    for i in range(n):
        rec = data[32 * i: 32 * (i + 1)]
        means[i] = np.frombuffer(rec[:12], "<f4")
        log_scales[i] = [math.log(s) for s in np.frombuffer(rec[12:24], "<f4")]
        sh[i, 0] = [(c / 255 - 0.5) / 0.28209479177387814 for c in rec[24:27]]
        opacities[i] = min(max(rec[27] / 255, 1e-6), 1 - 1e-6)
        quats[i] = [b / 255 * 2 - 1 for b in rec[28:32]]
    return means, quats, log_scales, opacities, sh


def test_reader_matches_the_format_description(tmp_path: Path) -> None:
    data = records(np.random.default_rng(0), 50)
    (tmp_path / "s.splat").write_bytes(data)
    scene = load_scene(tmp_path / "s.splat")  # no magic: by its suffix
    assert scene.sh_degree == 0 and scene_info(tmp_path / "s.splat") == (50, 0)
    assert_matches(scene, *reference_decode(data))


@pytest.mark.real_data
@pytest.mark.parametrize("name", ["plant", "tarot-box"])
def test_real_captures_match_splat_transform(name: str) -> None:
    files = list((CAPTURES / name).glob("*.splat"))
    if not files:
        pytest.skip(f"shared data not available: {CAPTURES / name} is absent (it lives beside the repository)")
    check_against_sample(load_splat(files[0]), DATA / f"{name}.npz")
