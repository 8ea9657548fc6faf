"""shards.py: atomic, deterministic WebDataset tars, done markers, index.json, stats.json (SPEC section 5)."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.shards import webdataset as shards
from scenesplat_stereo.shards.webdataset import ShardWriter, iter_shard


def members_of(i: int, scene: str = "sc", subset: str = "ScanNetGS", psnr: float | None = 33.0, targets: int = 2) -> dict:
    meta = {"scene": scene, "subset": subset, "teacher_psnr": psnr, "targets": [np.eye(4).tolist()] * targets}
    out = {"json": json.dumps(meta).encode(), "left.jpg": bytes([i]) * (100 + i), "right.jpg": b"R" * i}
    for j in range(targets):
        out[f"target_{j:02d}.jpg"] = bytes([j, i]) * 7
        out[f"mask_{j:02d}.png"] = b"M" * (j + 1)
    return out


def write(root: Path, n: int, per: int, first: int = 0, scene: str = "sc") -> list[int]:
    with ShardWriter(root, "train", per, first_shard=first) as w:
        for i in range(n):
            w.add(f"{scene}__{i:06d}", members_of(i, scene))
    return w.written


def webdataset_groups(path: Path) -> list[tuple[str, dict[str, bytes]]]:
    """WebDataset's grouping written out independently: key = name up to the first '.' of the base name,
    consecutive members with the same key form one sample."""
    groups: list[tuple[str, dict[str, bytes]]] = []
    with tarfile.open(path) as tar:
        for m in tar.getmembers():
            key, ext = m.name.split(".", 1)
            if not groups or groups[-1][0] != key:
                groups.append((key, {}))
            groups[-1][1][ext] = tar.extractfile(m).read()
    return groups


def test_shards_roll_over_and_read_back(tmp_path):
    assert write(tmp_path, 7, 3) == [0, 1, 2]
    paths = sorted((tmp_path / "train").glob("shard-*.tar"))
    assert [p.name for p in paths] == ["shard-000000.tar", "shard-000001.tar", "shard-000002.tar"]
    got = [s for p in paths for s in webdataset_groups(p)]
    assert [k for k, _ in got] == [f"sc__{i:06d}" for i in range(7)]
    for i, (key, members) in enumerate(got):
        assert members == members_of(i)
    assert [s for p in paths for s in iter_shard(p)] == got
    # no temp files left
    assert not list((tmp_path / "train").glob(".tmp-*"))


def test_tar_headers_are_fixed_and_bytes_identical(tmp_path):
    write(tmp_path / "a", 5, 2)
    write(tmp_path / "b", 5, 2)
    for name in ("shard-000000.tar", "shard-000001.tar", "shard-000002.tar"):
        assert (tmp_path / "a/train" / name).read_bytes() == (tmp_path / "b/train" / name).read_bytes()
    with tarfile.open(tmp_path / "a/train/shard-000000.tar") as tar:
        infos = tar.getmembers()
    assert all(m.mtime == 0 and m.uid == 0 and m.gid == 0 and m.uname == "" and m.mode == 0o644 for m in infos)
    names = [m.name for m in infos]
    assert names[:3] == ["sc__000000.json", "sc__000000.left.jpg", "sc__000000.mask_00.png"]  # sorted per sample


def test_shard_bytes_are_what_tarfile_writes(tmp_path):
    """The writer hands tarfile's output to the file one sample at a time: the bytes must be exactly those
    of a tar written member by member by tarfile itself (same headers), and the done marker's hash theirs."""
    write(tmp_path, 3, 3)
    expected = io.BytesIO()
    with tarfile.open(fileobj=expected, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for i in range(3):
            members = members_of(i)
            for suffix in sorted(members):
                info = tarfile.TarInfo(f"sc__{i:06d}.{suffix}")
                info.size, info.mtime, info.mode, info.uid, info.gid, info.uname, info.gname = (
                    len(members[suffix]), 0, 0o644, 0, 0, "", "")
                tar.addfile(info, io.BytesIO(members[suffix]))
    data = (tmp_path / "train/shard-000000.tar").read_bytes()
    assert data == expected.getvalue()
    assert shards.read_done(tmp_path, "train", 0)["sha256"] == hashlib.sha256(data).hexdigest()


def test_a_sample_with_a_bad_member_adds_nothing(tmp_path):
    with ShardWriter(tmp_path, "train", 2) as w:
        w.add("sc__000000", members_of(0))
        with pytest.raises(ValueError, match="suffix"):
            w.add("sc__000001", {"json": b"{}", "left.jpg": b"L", "zz/bad": b""})  # the bad one sorts last
        w.add("sc__000002", members_of(2))
    assert [k for k, _ in iter_shard(tmp_path / "train/shard-000000.tar")] == ["sc__000000", "sc__000002"]


def test_exception_leaves_no_partial_shard(tmp_path):
    with pytest.raises(RuntimeError):
        with ShardWriter(tmp_path, "train", 3) as w:
            for i in range(5):
                w.add(f"sc__{i:06d}", members_of(i))
            raise RuntimeError("killed")
    folder = tmp_path / "train"
    assert sorted(p.name for p in folder.iterdir() if p.is_file()) == ["shard-000000.tar"]
    assert shards.read_done(tmp_path, "train", 0)["num_samples"] == 3
    assert shards.read_done(tmp_path, "train", 1) is None


def test_stale_temp_and_old_marker_are_replaced(tmp_path):
    folder = tmp_path / "train"
    folder.mkdir()
    (folder / ".tmp-shard-000004.tar").write_bytes(b"half a tar from a killed run")
    write(tmp_path, 2, 2, first=4)
    assert not (folder / ".tmp-shard-000004.tar").exists()
    assert shards.read_done(tmp_path, "train", 4)["keys"] == ["sc__000000", "sc__000001"]
    # a marker that does not match the tar's size is not "done"
    (folder / "shard-000004.tar").write_bytes(b"truncated")
    assert shards.read_done(tmp_path, "train", 4) is None
    (folder / "shard-000004.tar").unlink()
    assert shards.read_done(tmp_path, "train", 4) is None


def test_bad_keys_and_members_are_refused(tmp_path):
    with ShardWriter(tmp_path, "train", 10) as w:
        for key in ("a.b__000000", "a/b", "", "a b"):
            with pytest.raises(ValueError, match="key"):
                w.add(key, {"json": b"{}"})
        with pytest.raises(ValueError, match="suffix"):
            w.add("ok__000000", {"../x": b""})
        w.add("ok__000001", members_of(1))
        with pytest.raises(ValueError, match="already"):
            w.add("ok__000001", members_of(1))
    with pytest.raises(ValueError):
        ShardWriter(tmp_path, "train", 0)


def test_iter_shard_refuses_scattered_samples(tmp_path):
    path = tmp_path / "x.tar"
    with tarfile.open(path, "w") as tar:
        for name in ("a.json", "b.json", "a.left.jpg"):
            info = tarfile.TarInfo(name)
            info.size = 0
            tar.addfile(info)
    with pytest.raises(ValueError, match="not contiguous"):
        list(iter_shard(path))


def test_index_and_stats(tmp_path):
    write(tmp_path, 3, 2, first=0, scene="alpha")
    write(tmp_path, 1, 2, first=2, scene="beta")
    with ShardWriter(tmp_path, "val", 5) as w:
        w.add("gamma__000000", members_of(0, "gamma", "ScanNetPPGS-V2", 36.0, targets=4))
        w.add("delta__000000", members_of(0, "delta", "ScanNetPPGS-V2", None, targets=4))
    index = shards.write_index(tmp_path, "train")
    assert json.loads((tmp_path / "train/index.json").read_text()) == index
    assert index["num_shards"] == 3 and index["num_samples"] == 4
    assert [s["name"] for s in index["shards"]] == ["shard-000000.tar", "shard-000001.tar", "shard-000002.tar"]
    assert index["shards"][2]["keys"] == ["beta__000000"]
    stats = shards.collect_stats(tmp_path)
    gs = stats["subsets"]["ScanNetGS"]
    assert gs["splits"]["train"] == {"scenes": 2, "pairs": 4, "targets": 8, "teacher_psnr": 33.0}
    pp = stats["subsets"]["ScanNetPPGS-V2"]
    assert pp["splits"]["val"] == {"scenes": 2, "pairs": 2, "targets": 8, "teacher_psnr": 36.0}  # None skipped
    assert stats["total"] == {"train": {"scenes": 2, "pairs": 4, "targets": 8},
                              "val": {"scenes": 2, "pairs": 2, "targets": 8}}
    shards.write_stats(tmp_path, stats)
    assert json.loads((tmp_path / "stats.json").read_text()) == stats


def test_planned_shards_follow_the_plan_and_discard(tmp_path):
    sink = shards.PlannedShards(tmp_path, "train", [(5, ["a__000000", "a__000001"]), (6, ["a__000002"])])
    sink("a__000000", members_of(0, "a"))
    sink("a__000001", members_of(1, "a"))
    assert sink.done == 1 and shards.read_done(tmp_path, "train", 5)["keys"] == ["a__000000", "a__000001"]
    with pytest.raises(RuntimeError, match="planned"):
        sink("a__000009", members_of(9, "a"))
    sink("a__000002", members_of(2, "a"))
    assert (sink.done, sink.pairs) == (2, 3)
    partial = shards.PlannedShards(tmp_path, "val", [(0, ["b__000000", "b__000001"])])
    partial("b__000000", members_of(0, "b"))
    partial.discard()
    assert not [p for p in (tmp_path / "val").rglob("*") if p.is_file()]


def test_planned_shards_count_a_shard_finished_just_before_an_interrupt(tmp_path, monkeypatch):
    """Ctrl-C can land after a writer wrote its shard's done marker and before the sink counted it (a CI run of
    ``sgmodel encode`` reported "0 of 4 shards written" with one on disk): ``finished`` counts what is on
    disk."""
    sink = shards.PlannedShards(tmp_path, "train", [(0, ["a__000000"]), (1, ["a__000001", "a__000002"])])
    add = shards.ShardWriter.add

    def add_then_interrupt(self, key, members):
        add(self, key, members)
        raise KeyboardInterrupt

    monkeypatch.setattr(shards.ShardWriter, "add", add_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        sink("a__000000", members_of(0, "a"))  # shard 0 finished, then the interrupt before the sink's count
    sink.discard()
    assert sink.done == 0 and sink.finished() == 1  # the count missed the shard; it is on disk
    assert shards.read_done(tmp_path, "train", 0)["keys"] == ["a__000000"]


def test_remove_unplanned(tmp_path):
    write(tmp_path, 6, 2)  # shards 0, 1, 2
    (tmp_path / "train/.tmp-shard-000009.tar").write_bytes(b"x")
    assert shards.remove_unplanned(tmp_path, "train", {0, 2}) == 1
    assert sorted(p.name for p in (tmp_path / "train").iterdir() if p.is_file()) == ["shard-000000.tar", "shard-000002.tar"]
    assert sorted(shards.finished_shards(tmp_path, "train")) == [0, 2]
