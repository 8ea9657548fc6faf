"""The ReplicaGS recipe: ``scenesplat-stereo build --preset replicags`` (paper appendices B and C)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scenesplat_stereo.build.inspection import inspect_dataset
from scenesplat_stereo.build.protocol import test_frames
from scenesplat_stereo.build.run import settings_from_args
from scenesplat_stereo.build.settings import PRESETS
from scenesplat_stereo.cli import build_parser
from scenesplat_stereo.shards.sample import SampleMeta
from scenesplat_stereo.shards.webdataset import iter_shard
from tests.conftest import REPLICAGS_FRAMES, REPLICAGS_SCENES


def settings(*flags: str):
    return settings_from_args(build_parser().parse_args(["build", "--teachers", "t", "--out", "o", "--device", "cpu",
                                                         *flags]))


def test_the_preset_sets_exactly_the_papers_values():
    s = settings("--preset", "replicags")
    assert (s.split_mode, s.resolution, s.baseline, s.rho, s.targets, s.min_psnr, s.max_frames) == \
        ("test", None, 0.10, None, 10, 30.0, None)
    plain = settings()
    assert set(PRESETS["replicags"]) == {"split_mode", "resolution", "baseline", "rho", "targets", "min_psnr",
                                         "max_frames"}
    changed = {k for k in PRESETS["replicags"] if getattr(s, k) != getattr(plain, k)}
    assert changed == {"split_mode", "baseline"}  # the rest of the recipe is the build's default
    others = [f for f in type(s).__dataclass_fields__ if f not in PRESETS["replicags"]]
    assert all(getattr(s, f) == getattr(plain, f) for f in others if f not in ("progress",))


def test_flags_given_beside_the_preset_win():
    s = settings("--preset", "replicags", "--baseline", "0.2", "--rho", "0.3", "--targets", "4", "--resolution",
                 "600x340", "--max-frames", "7", "--min-psnr", "none")
    assert (s.baseline, s.rho, s.targets, s.resolution, s.max_frames, s.min_psnr) == (0.2, 0.3, 4, (600, 340), 7, None)
    # a flag typed with the value that happens to be the build's default still wins over the preset
    assert settings("--preset", "replicags", "--split-mode", "trainval").split_mode == "trainval"
    assert settings("--split-mode", "trainval").split_mode == "trainval" and settings().baseline is None


def test_one_hundred_evenly_spaced_poses_of_a_2000_frame_trajectory():
    frames = test_frames(2000)
    assert len(frames) == 100 and frames[0] == 0 and frames[-1] == 1999
    np.testing.assert_array_equal(frames, np.round(np.arange(100) * 1999 / 99))
    assert 8 * len(frames) == 800 and 8 * len(frames) * 10 == 8000  # the paper's 800 pairs, 8000 targets


def test_a_replicags_build(replicags_dataset):
    metas = [SampleMeta.from_json(m["json"], k) for tar in sorted((replicags_dataset / "test").glob("*.tar"))
             for k, m in iter_shard(tar)]
    assert len(metas) == REPLICAGS_SCENES * REPLICAGS_FRAMES
    psnr = {m.scene: m.teacher_psnr for m in metas}
    for m in metas:
        assert m.subset == "ReplicaGS" and m.baseline == 0.10 and m.num_targets == 10
        assert (m.width, m.height) == (96, 72)  # the teachers' native size
        tier_rho = 0.10 if psnr[m.scene] < 35 else 0.20 if psnr[m.scene] < 40 else 0.30
        assert m.rho == tier_rho
    assert sorted({m.rho for m in metas}) == [0.1, 0.2, 0.3]  # one demo room per tier
    assert sorted(m.frame for m in metas if m.scene == metas[0].scene) == list(range(REPLICAGS_FRAMES))
    bench = json.loads((replicags_dataset / "benchmark.json").read_text())
    assert bench["masked"] is True and bench["source"] == "rendered" and "alpha >= 0.5" in bench["protocol"]
    stats = json.loads((replicags_dataset / "stats.json").read_text())
    assert stats["subsets"]["ReplicaGS"]["splits"]["test"]["targets"] == REPLICAGS_SCENES * REPLICAGS_FRAMES * 10
    assert not inspect_dataset(replicags_dataset, contact_sheet=replicags_dataset.parent / "sheet.png").problems


def test_preset_refusals_exit_2(tmp_path, capsys):
    from scenesplat_stereo.cli import main

    with pytest.raises(SystemExit) as e:
        main(["build", "--teachers", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "replica"])
    assert e.value.code == 2 and "--preset" in capsys.readouterr().err
    assert main(["build", "--teachers", str(tmp_path / "none"), "--out", str(tmp_path / "o"), "--preset", "replicags",
                 "--device", "cpu", "--no-progress"]) == 2
    assert not (tmp_path / "o").exists()
