"""Real captures as they are published (../shared/data/captures: PlayCanvas .sog, antimatter15 .splat; a
streamed SOG when STREAMED_SCENES holds ``playbot/`` or ``flowers/``): each renders through ``scenesplat-stereo
render`` and builds as a teacher from a folder holding only that file, and the built dataset passes ``inspect``; at tiny
size on the CPU."""

from __future__ import annotations

from pathlib import Path

import pytest

from scenesplat_stereo.build.inspection import inspect_dataset
from scenesplat_stereo.build.run import build
from scenesplat_stereo.build.settings import BuildSettings
from scenesplat_stereo.cli import main
from scenesplat_stereo.scene.teachers import OrbitSpec
from scenesplat_stereo.shards.encode import decode_image
from tests.support.paths import CAPTURES, STREAMED

SOURCES = {"sog": CAPTURES / "statue-massa" / "massa.sog", "splat": CAPTURES / "plant" / "plant.splat",
           "streamed": STREAMED / "playbot", "streamed-flowers": STREAMED / "flowers"}


@pytest.mark.real_data
@pytest.mark.parametrize("kind", sorted(SOURCES))
def test_capture_renders_and_builds_as_a_teacher(tmp_path: Path, kind: str) -> None:
    source = SOURCES[kind]
    if not source.exists():
        pytest.skip(f"real data not available: {source} is absent (shared data, or STREAMED_SCENES for playbot and "
                    "flowers)")
    assert main(["render", str(source), "--out", str(tmp_path / "frames"), "--device", "cpu",
                 "--orbit", "radius=2.5,frames=1,size=48x32"]) == 0
    frame = decode_image((tmp_path / "frames" / "frame_0000.png").read_bytes(), "png")
    assert frame.shape[:2] == (32, 48) and frame.max() > 30  # something in view
    teacher = tmp_path / "teachers" / kind
    teacher.mkdir(parents=True)
    (teacher / source.name).symlink_to(source)  # the folder holds only the capture (or the streamed folder)
    if kind.startswith("streamed"):
        (teacher / source.name).unlink()
        teacher.rmdir()
        teacher.symlink_to(source, target_is_directory=True)
    report = build(BuildSettings(teachers=tmp_path / "teachers", out=tmp_path / "out", min_psnr=None,
                                 orbit=OrbitSpec(radius=2.5, n_frames=2, width=32, height=24), val_scenes=0,
                                 targets=2, baseline=0.1, rho=0.2, progress=False, workers=1, device="cpu"))
    assert not report.failed and report.planned["train"]["pairs"] == 2, report
    checked = inspect_dataset(tmp_path / "out", progress=False)
    assert checked.ok, checked.problems
