"""scenesplat_stereo.scene.lod: streamed SOG scenes (lod-meta.json + SOG units) read at one level, on a synthetic scene
built here from the format description, and on the two real ones PROVENANCE names (playcanvas/engine's
examples/assets/splats/playbot and flowers, not kept in the repository: set STREAMED_SCENES to a folder holding
``playbot/`` and ``flowers/``, or put them in ../shared/data/streamed; skipped otherwise) against
splat-transform 3.7.0's decode (tests/data/captures)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tests.scenesplat_stereo.scene.test_sog import DATA, assert_matches, check_against_sample

from scenesplat_stereo.scene.lod import LodError, load_lod
from scenesplat_stereo.scene.scene_files import load_scene, scene_info
from tests.support.paths import STREAMED
from tests.support.sog_helpers import make_sog, reference_decode


def make_streamed(root: Path, counts: dict | None = None) -> tuple[Path, list]:
    """Three units: "0_0" (30 Gaussians) and "0_1" (20) of level 0, "1_0" (12) of level 1; two leaf nodes, each
    holding rows of every level. Returns (folder, [unit dicts of make_sog])."""
    units = [make_sog(root / name, n, 1, seed=i) for i, (name, n) in enumerate((("0_0", 30), ("0_1", 20), ("1_0", 12)))]
    leaf = lambda lods: {"bound": {"min": [0, 0, 0], "max": [1, 1, 1]}, "lods": lods}  # noqa: E731
    tree = {"children": [leaf({"0": {"file": 2, "offset": 18, "count": 12}, "1": {"file": 1, "offset": 0, "count": 7}}),
                         leaf({"0": {"file": 2, "offset": 0, "count": 18}, "1": {"file": 1, "offset": 7, "count": 5}}),
                         leaf({"0": {"file": 0, "offset": 0, "count": 20}})]}
    meta = {"version": 1, "lodLevels": 2, "counts": [50, 12] if counts is None else counts,
            "filenames": ["0_1/meta.json", "1_0/meta.json", "0_0/meta.json"], "tree": tree}
    (root / "lod-meta.json").write_text(json.dumps(meta))
    return root, units


def test_levels_read_their_rows(tmp_path: Path) -> None:
    root, (u00, u01, u10) = make_streamed(tmp_path / "scene")
    ref = lambda u: reference_decode(u)  # noqa: E731
    # level 0: file 0 (0_1, all 20 rows), then file 2 (0_0) rows 0..17 and 18..29, in offset order
    want = [np.concatenate([a, b]) for a, b in zip(ref(u01), ref(u00))]
    assert_matches(load_scene(root), *want)
    assert scene_info(root) == (50, 1) and scene_info(root / "lod-meta.json", lod=1) == (12, 1)
    assert_matches(load_lod(root / "lod-meta.json", 1), *ref(u10))
    with pytest.raises(LodError, match="level 2: no Gaussians at that level"):
        load_lod(root, 2)


def test_counts_that_do_not_match_the_tree_are_refused(tmp_path: Path) -> None:
    root, _ = make_streamed(tmp_path / "scene", counts=[51, 12])
    with pytest.raises(LodError, match=r"lod-meta.json: counts: \[51, 12\] but the tree references \[50, 12\]"):
        load_lod(root)


@pytest.mark.real_data
@pytest.mark.parametrize("scene", ["playbot", "flowers"])
@pytest.mark.parametrize("level", [0, 3])
def test_real_streamed_scene_matches_splat_transform(scene: str, level: int) -> None:
    if not (STREAMED / scene / "lod-meta.json").is_file():
        pytest.skip(f"streamed scene not available: {STREAMED / scene} is absent (fetch playcanvas/engine's "
                    f"examples/assets/splats/{scene}, named in ../shared/data/PROVENANCE.md, and set STREAMED_SCENES "
                    "to its parent folder)")
    check_against_sample(load_lod(STREAMED / scene, level), DATA / f"{scene}-lod{level}.npz")
