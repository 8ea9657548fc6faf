"""Shared pytest fixtures: the read-only shared data beside the repository (skipped when absent)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.support.paths import SHARED_DATA

GUITAR_DIR = "teachers/playcanvas-guitar"


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"shared data not available: {path} is absent (it lives beside the repository)")
    return path


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared data folder ``<repo>/../shared/data``; skips the test when it is absent."""
    return _require(SHARED_DATA)


@pytest.fixture(scope="session")
def guitar_ply(shared_data: Path) -> Path:
    """The PlayCanvas guitar (90,854 Gaussians, SH degree 0) in the INRIA layout, float32 little-endian."""
    return _require(shared_data / GUITAR_DIR / "point_cloud.ply")


@pytest.fixture(scope="session")
def guitar_compressed_ply(shared_data: Path) -> Path:
    """The same guitar in the PlayCanvas/SuperSplat compressed layout (the source of ``guitar_ply``)."""
    return _require(shared_data / GUITAR_DIR / "guitar.compressed.ply")


#: The demo dataset of ``demo_dataset``: 3 procedural rooms at 96x72, 6 frames each, one validation scene.
DEMO_SCENES, DEMO_FRAMES, DEMO_SIZE = 3, 6, (96, 72)
DEMO_SAMPLES_PER_SHARD = 4


@pytest.fixture(scope="session")
def demo_dataset(tmp_path_factory) -> Path:
    """A tiny SceneSplat-Stereo build of the demo teachers (built once per test session, on the CPU):
    ``train`` 2 scenes x 6 pairs x 10 targets in 4 shards (4 + 2 samples per scene), ``val`` 1 scene x 5
    pairs x 4 targets in 2 shards, 96x72 images, ``left_depth.exr`` in every sample. Returns the output
    folder (``<out>/<split>/index.json``, shards, ``stats.json``). Read-only: copy it to damage it."""
    from scenesplat_stereo.build.demo import write_demo_teachers
    from scenesplat_stereo.build.run import BuildSettings, build

    base = tmp_path_factory.mktemp("demo_dataset")
    teachers, out = base / "teachers", base / "shards"
    write_demo_teachers(teachers, n_scenes=DEMO_SCENES, n_frames=DEMO_FRAMES, width=DEMO_SIZE[0],
                        height=DEMO_SIZE[1], num_gaussians=2000, progress=False)
    report = build(BuildSettings(teachers=teachers, out=out, val_scenes=1, with_depth=True,
                                 samples_per_shard=DEMO_SAMPLES_PER_SHARD, workers=1, batch_pairs=6,
                                 progress=False))
    if report.failed:
        raise RuntimeError(f"demo dataset build failed: {[r.error for r in report.failed]}")
    return out


@pytest.fixture(scope="session")
def stereonvs_scenes(tmp_path_factory) -> list:
    """A StereoNVS-Real-like ROOT of two scenes rendered at known cameras (``tests/support/stereonvs_fixture.py``):
    "lab" with JPEG images, "office" with PNG images; 7 stereo pairs each, 96x48 pixels. Returns the
    ``FixtureScene`` records (their ``folder.parent`` is ROOT). Read-only: copy it to damage it."""
    from tests.support.stereonvs_fixture import write_scene

    root = tmp_path_factory.mktemp("stereonvs") / "root"
    return [write_scene(root, "lab", seed=1, suffix=".jpg"), write_scene(root, "office", seed=2, suffix=".png")]


@pytest.fixture(scope="session")
def stereonvs_dataset(stereonvs_scenes, tmp_path_factory) -> Path:
    """``scenesplat-stereo import stereonvs`` of ``stereonvs_scenes`` (baseline 0.12 m): OUT with a test
    split of 9 samples, 14 targets, in shards of 4 samples. Read-only."""
    from scenesplat_stereo.captured.stereonvs import import_stereonvs
    from tests.support.stereonvs_fixture import BASELINE

    out = tmp_path_factory.mktemp("stereonvs_out") / "StereoNVS"
    import_stereonvs(stereonvs_scenes[0].folder.parent, out, BASELINE, samples_per_shard=4, progress=False)
    return out


#: ``replicags_dataset``: 3 demo rooms (one per PSNR tier) at 96x72, 4 frames each, in a ``ReplicaGS`` folder.
REPLICAGS_SCENES, REPLICAGS_FRAMES = 3, 4


@pytest.fixture(scope="session")
def replicags_dataset(tmp_path_factory) -> Path:
    """``scenesplat-stereo build --preset replicags`` of demo teachers in ``<teachers>/ReplicaGS/`` (so their
    subset is ReplicaGS): a test split of 3 scenes x 4 pairs x 10 targets, B = 0.1 m, rho by tier,
    ``benchmark.json`` masked. Returns OUT (its ``build.json`` records the settings). Read-only."""
    from scenesplat_stereo.build.demo import write_demo_teachers
    from scenesplat_stereo.build.run import build, settings_from_args
    from scenesplat_stereo.cli import build_parser

    base = tmp_path_factory.mktemp("replicags")
    teachers, out = base / "teachers", base / "ReplicaGS"
    for folder in write_demo_teachers(teachers / "ReplicaGS", n_scenes=REPLICAGS_SCENES, n_frames=REPLICAGS_FRAMES,
                                      width=96, height=72, num_gaussians=2000, progress=False):
        meta = json.loads((folder / "scene.json").read_text())
        del meta["subset"]  # the subset comes from the folder's name, as for downloaded teachers
        (folder / "scene.json").write_text(json.dumps(meta))
    args = build_parser().parse_args(["build", "--teachers", str(teachers), "--out", str(out), "--preset", "replicags",
                                      "--workers", "1", "--device", "cpu", "--no-progress"])
    report = build(settings_from_args(args))
    if report.failed:
        raise RuntimeError(f"ReplicaGS-style build failed: {[r.error for r in report.failed]}")
    return out


@pytest.fixture(scope="session")
def raw_rig(tmp_path_factory):
    """``raw_rig(model)``: a raw stereo rig's pair of a demo room (scripts/inputs/rig_pair.py; "radtan" or
    "equidistant" lenses) written once per session: namespace(folder, rig = the ground truth, scene)."""
    import argparse

    from scripts.inputs.rig_pair import room, write_rig

    cache, scene = {}, []

    def make(model: str = "radtan"):
        if model not in cache:
            scene[:] = scene or [room()]
            folder = tmp_path_factory.mktemp(f"rig_{model}")
            cache[model] = argparse.Namespace(folder=folder, rig=write_rig(folder, model, scene[0]), scene=scene[0])
        return cache[model]

    return make
