"""sgmodel.data.loader: square crop and K, masks, target viewmats, target draws, worker/rank splits, reproducible
training order, bad input (SPEC section 7, the Batch contract)."""

from __future__ import annotations

import io
import json
import shutil
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch

from scenesplat_stereo.shards.encode import decode_image
from scenesplat_stereo.shards.sample import SampleMeta
from scenesplat_stereo.shards.webdataset import iter_shard
from sgmodel.data import sample_order
from sgmodel.data import loader as loader_mod
from sgmodel.data.loader import DataError, ShardStream, make_loader
from sgmodel.data.square_crop import SquareCrop


def project(K: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Pinhole projection (float64) of camera-frame points [..., 3] to continuous pixel coordinates."""
    return np.stack([K[0, 0] * p[..., 0] / p[..., 2] + K[0, 2], K[1, 1] * p[..., 1] / p[..., 2] + K[1, 2]], -1)


def blob_image(w: int, h: int, uv: np.ndarray, sigma: float = 2.5) -> np.ndarray:
    """A Gaussian blob centred at continuous coordinate uv (pixel centres at +0.5)."""
    x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.exp(-((x - uv[0]) ** 2 + (y - uv[1]) ** 2) / (2 * sigma ** 2)).astype(np.float32)[..., None]


def centroid(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    m = img[..., 0].astype(np.float64)
    return np.array([(x * m).sum() / m.sum(), (y * m).sum() / m.sum()])


@pytest.mark.parametrize("w, h, size", [(96, 72, 48), (96, 72, 160), (72, 96, 64), (64, 64, 50), (101, 70, 33)])
def test_crop_moves_k_with_the_pixels(w, h, size):
    K = np.array([[80.0, 0, 47.3], [0, 81.0, 35.9], [0, 0, 1]])
    crop = SquareCrop.plan(w, h, size)
    assert min(crop.scaled_width, crop.scaled_height) == size
    K2 = crop.intrinsics(K)
    for point in ([0.1, -0.05, 2.0], [-0.2, 0.1, 3.0]):
        p = np.array(point)
        uv = project(K, p)
        got = centroid(crop.image(blob_image(w, h, uv, sigma=3.0 * max(1.0, w / size))))
        np.testing.assert_allclose(got, project(K2, p), atol=0.3)
    # the optical axis through the image centre stays at the crop centre (centre crop)
    Kc = np.array([[80.0, 0, w / 2], [0, 80.0, h / 2], [0, 0, 1]])
    np.testing.assert_allclose(project(crop.intrinsics(Kc), np.array([0, 0, 1.0])), [size / 2, size / 2], atol=0.5)


def test_mask_resize_is_nearest_pixel_centre():
    rng = np.random.default_rng(0)
    mask = (rng.random((72, 96, 1)) > 0.5).astype(np.uint8) * 255
    crop = SquareCrop.plan(96, 72, 48)  # scale 2/3: no pixel centre falls on a source pixel edge
    got = crop.nearest(mask)
    s = 2 / 3
    x0 = (64 - 48) // 2
    cols = np.floor((np.arange(48) + x0 + 0.5) / s).astype(int)
    rows = np.floor((np.arange(48) + 0.5) / s).astype(int)
    np.testing.assert_array_equal(got[..., 0], mask[rows][:, cols, 0])
    assert set(np.unique(got)) <= {0, 255}


def test_too_small_image_is_refused():
    SquareCrop.plan(64, 48, 192)  # 4x is accepted
    with pytest.raises(ValueError, match="too small"):
        SquareCrop.plan(64, 47, 192)


def read_all(root: Path, split: str) -> dict[str, dict[str, bytes]]:
    index = json.loads((root / split / "index.json").read_text())
    return {k: m for s in index["shards"] for k, m in iter_shard(root / split / s["name"])}


def test_batch_contract_viewmats_and_targets(demo_dataset):
    size = 64
    batch = next(iter(make_loader(demo_dataset, "train", 3, size, 4, seed=1)))
    B, T = 3, 4
    shapes = {"left": (B, 3, size, size), "right": (B, 3, size, size), "K": (B, 3, 3), "baseline": (B,),
              "targets": (B, T, 3, size, size), "masks": (B, T, 1, size, size), "target_viewmats": (B, T, 4, 4),
              "target_Ks": (B, T, 3, 3), "target_ids": (B, T), "depth": (B, 1, size, size)}
    for name, shape in shapes.items():
        assert tuple(batch[name].shape) == shape, name
    assert batch["masks"].dtype == torch.bool and batch["target_ids"].dtype == torch.int64
    assert all(batch[n].dtype == torch.float32 for n in ("left", "K", "baseline", "targets", "target_viewmats", "depth"))
    assert 0 <= batch["left"].min() and batch["left"].max() <= 1 and batch["depth"].max() > 0.5
    members = read_all(demo_dataset, "train")
    for b, key in enumerate(batch["keys"]):
        meta = SampleMeta.from_json(members[key]["json"], key)
        assert batch["scenes"][b] == meta.scene and batch["baseline"][b] == pytest.approx(meta.baseline)
        ids = batch["target_ids"][b].tolist()
        assert len(set(ids)) == T and set(ids) <= set(meta.target_ids)
        # a point in the left camera frame projects into each target where the world computation says
        p_left = np.array([0.3, -0.2, 2.5])
        world = meta.c2w_left @ np.append(p_left, 1.0)
        for t, j in enumerate(ids):
            c2w_t = meta.targets[meta.target_ids.index(j)]
            R, c = c2w_t[:3, :3], c2w_t[:3, 3]
            want = project(batch["target_Ks"][b, t].double().numpy(), R.T @ (world[:3] - c))
            p_t = batch["target_viewmats"][b, t].double().numpy() @ np.append(p_left, 1.0)
            got = project(batch["target_Ks"][b, t].double().numpy(), p_t[:3])
            np.testing.assert_allclose(got, want, atol=1e-3)
            # the target image and mask are the stored ones of direction j
            crop = SquareCrop.plan(meta.width, meta.height, size)
            img = crop.image(decode_image(members[key][f"target_{j:02d}.jpg"], "jpg").astype(np.float32) / 255)
            np.testing.assert_allclose(batch["targets"][b, t].numpy(), img.transpose(2, 0, 1), atol=1e-6)
        np.testing.assert_allclose(batch["K"][b].numpy(), crop.intrinsics(meta.K), rtol=1e-6)


def collect(loader, steps: int) -> list[tuple[list[str], list[list[int]]]]:
    out = []
    for batch, _ in zip(loader, range(steps)):
        out.append((batch["keys"], batch["target_ids"].tolist()))
    return out


def test_training_is_endless_seeded_and_resumable(demo_dataset):
    kw = dict(resolution=32, targets=4, shuffle_buffer=4)
    run = collect(make_loader(demo_dataset, "train", 3, seed=5, **kw), 10)  # 12 samples: 2.5 epochs
    first_epoch = [k for keys, _ in run[:4] for k in keys]
    assert sorted(first_epoch) == sorted(read_all(demo_dataset, "train"))  # each sample once per epoch
    assert [k for keys, _ in run[4:8] for k in keys] != first_epoch  # reshuffled
    assert collect(make_loader(demo_dataset, "train", 3, seed=5, **kw), 10) == run
    assert collect(make_loader(demo_dataset, "train", 3, seed=6, **kw), 10) != run
    assert collect(make_loader(demo_dataset, "train", 3, seed=5, start_step=6, **kw), 4) == run[6:]
    draws = [tuple(ids) for _, step in run for ids in step]
    assert all(len(set(d)) == 4 and set(d) <= set(range(10)) for d in draws)
    assert len(set(draws)) > 20 and set().union(*draws) == set(range(10))


def test_training_resume_with_workers(demo_dataset):
    kw = dict(resolution=32, targets=4, num_workers=2, shuffle_buffer=3)
    run = collect(make_loader(demo_dataset, "train", 2, seed=3, **kw), 9)
    assert collect(make_loader(demo_dataset, "train", 2, seed=3, start_step=5, **kw), 4) == run[5:]


def test_a_loader_worker_keeps_its_last_batches_and_hands_over_the_same_ones(demo_dataset):
    """``KeptBatches``: each worker's collate keeps its last ``KEPT_BATCHES`` batches (so that the worker, not the
    consuming process, frees their shared memory: scripts/profile/loader_handover.py), the batches themselves
    unchanged; no worker or validation's (persistent) workers, no keeping."""
    keep = loader_mod.KeptBatches()
    samples = [sample for sample, _ in zip(ShardStream(demo_dataset, "val", 32, 2, train=False), range(2))]
    made = [keep(samples[:1]), keep(samples[1:2]), keep(samples[:2])]
    assert [id(b) for b in keep._kept] == [id(b) for b in made[-loader_mod.KEPT_BATCHES:]]
    assert loader_mod.KEPT_BATCHES >= 1 and torch.equal(made[2]["left"], loader_mod.collate(samples[:2])["left"])
    assert isinstance(make_loader(demo_dataset, "train", 2, 32, 4, num_workers=1).collate_fn, loader_mod.KeptBatches)
    assert make_loader(demo_dataset, "train", 2, 32, 4).collate_fn is loader_mod.collate
    assert make_loader(demo_dataset, "val", 2, 32, None, num_workers=1, train=False).collate_fn is loader_mod.collate
    kw = dict(resolution=32, targets=4, shuffle_buffer=3)
    assert collect(make_loader(demo_dataset, "train", 2, seed=3, num_workers=2, **kw), 4) == \
        collect(make_loader(demo_dataset, "train", 2, seed=3, **kw), 4)


@pytest.mark.parametrize("counts", [[4, 2, 4, 2], [4, 1], [3], [5, 5, 5, 1, 2, 7, 3]])
@pytest.mark.parametrize("streams", [1, 2, 3, 4, 6, 9])
def test_split_covers_every_sample_once(counts, streams):
    seen = [it for s in range(streams) for it in sample_order.validation_items(counts, s, streams)]
    assert sorted(seen) == [(s, i) for s, n in enumerate(counts) for i in range(n)]
    for epoch in range(3):
        items, emit = sample_order.train_walk(counts, 7 + streams, epoch, 4)
        assert sorted(items) == sorted(seen) and sorted(emit) == list(range(len(items)))


def test_batch_positions_tile_the_global_sequence():
    assert list(sample_order.batch_positions(3, 8)) == list(range(24, 32))
    halves = [list(sample_order.batch_positions(3, 8, r * 4, 4)) for r in range(2)]
    assert halves[0] + halves[1] == list(range(24, 32))
    with pytest.raises(ValueError, match="not in a batch of 8"):
        sample_order.batch_positions(0, 8, 6, 4)


def test_validation_loader_over_ranks_and_workers(demo_dataset):
    val = sorted(read_all(demo_dataset, "val"))
    for world, workers in [(1, 0), (2, 0), (3, 0), (2, 2)]:
        keys = []
        for rank in range(world):
            for batch in make_loader(demo_dataset, "val", 2, 32, None, rank=rank, world_size=world,
                                     num_workers=workers, train=False):
                assert batch["target_ids"][0].tolist() == [0, 1, 2, 3]
                keys += batch["keys"]
        assert sorted(keys) == val, (world, workers)
    once = [b["keys"] for b in make_loader(demo_dataset, "val", 2, 32, None, train=False)]
    assert once == [b["keys"] for b in make_loader(demo_dataset, "val", 2, 32, None, train=False)]


def rewrite(root: Path, split: str, shard: str, change) -> None:
    """Rewrite one shard with ``change(key, members) -> members`` applied to its first sample."""
    path = root / split / shard
    samples = list(iter_shard(path))
    samples[0] = (samples[0][0], change(samples[0][0], samples[0][1]))
    with tarfile.open(path, "w") as tar:
        for key, members in samples:
            for suffix in sorted(members):
                info = tarfile.TarInfo(f"{key}.{suffix}")
                info.size = len(members[suffix])
                tar.addfile(info, io.BytesIO(members[suffix]))


def edit_json(**fields):
    def change(key, members):
        doc = json.loads(members["json"]) | fields
        return members | {"json": json.dumps(doc).encode()}
    return change


@pytest.fixture
def copy(demo_dataset, tmp_path) -> Path:
    shutil.copytree(demo_dataset / "val", tmp_path / "val")
    return tmp_path


def first_val_batch(root: Path, resolution: int = 32, train: bool = False, targets=None):
    return next(iter(make_loader(root, "val", 4, resolution, targets, train=train)))


@pytest.mark.parametrize("change, message", [
    (lambda k, m: {n: d for n, d in m.items() if n != "target_02.jpg"}, "target_02.jpg: member missing"),
    (lambda k, m: {n: d for n, d in m.items() if n != "json"}, ".json: member missing"),
    (edit_json(targets=[], target_ids=[]), "field 'targets': no targets"),
    (edit_json(K=[[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]]), "field 'K'"),
    (edit_json(baseline=0.0), "field 'baseline'"),
    (edit_json(key="other__000000"), "field 'key'"),
    (lambda k, m: m | {"left.jpg": m["target_00.jpg"][:200]}, "left.jpg"),
    (lambda k, m: m | {"right.jpg": m["mask_00.png"]}, "right.jpg: decoded shape"),
])
def test_bad_samples_name_the_file_and_field(copy, change, message):
    rewrite(copy, "val", "shard-000000.tar", change)
    with pytest.raises(DataError, match="shard-000000.tar") as err:
        first_val_batch(copy)
    assert message in str(err.value)


def test_bad_folders_and_requests(copy, tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        make_loader(tmp_path / "nowhere", "val", 2)
    with pytest.raises(DataError, match="split 'train' does not exist"):
        make_loader(copy, "train", 2)
    (copy / "empty").mkdir()
    with pytest.raises(DataError, match="index.json: missing"):
        make_loader(copy, "empty", 2)
    (copy / "empty" / "index.json").write_text(json.dumps({"shards": []}))
    with pytest.raises(DataError, match="is empty"):
        make_loader(copy, "empty", 2)
    (copy / "val" / "shard-000001.tar").unlink()
    with pytest.raises(DataError, match="shard-000001.tar: listed in"):
        make_loader(copy, "val", 2)


def test_too_small_and_too_few_targets(demo_dataset):
    with pytest.raises(DataError, match="'width', 'height'.*too small"):
        first_val_batch(demo_dataset, resolution=300)  # 72 px short side < 300 / 4
    with pytest.raises(DataError, match="field 'targets': 4 stored, 5 asked"):
        first_val_batch(demo_dataset, train=True, targets=5)
    with pytest.raises(DataError, match="a batch of 6 pairs over all ranks is larger than the 5 samples"):
        ShardStream(demo_dataset, "val", 32, 4, world_size=6, rank=5)


def global_batches(root: Path, world: int, workers: int, steps: int, global_batch: int = 4, start: int = 0,
                   real_loader: bool = False) -> list[list[tuple[str, tuple[int, ...]]]]:
    """The (key, target ids) of every slot of global steps start .. start + steps - 1, ranks side by side,
    as ``world`` ranks with ``workers`` DataLoader workers each would make them."""
    local = global_batch // world
    per_rank = []
    for rank in range(world):
        kw = dict(resolution=32, targets=4, seed=11, rank=rank, world_size=world, start_step=start, shuffle_buffer=3)
        if real_loader:
            batches = collect(make_loader(root, "train", local, num_workers=workers, **kw), steps)
        else:  # the DataLoader's schedule: local batch j comes from worker j % workers, in that worker's order
            streams = [iter(ShardStream(root, "train", batch_size=local, **kw)._training(w, max(workers, 1)))
                       for w in range(max(workers, 1))]
            batches = []
            for j in range(steps):
                samples = [next(streams[j % max(workers, 1)]) for _ in range(local)]
                batches.append(([s["key"] for s in samples], [s["target_ids"].tolist() for s in samples]))
        per_rank.append(batches)
    return [[(k, tuple(ids)) for keys, targets in (b[step] for b in per_rank) for k, ids in zip(keys, targets)]
            for step in range(steps)]


def test_training_order_is_the_same_on_any_number_of_ranks_and_workers(demo_dataset):
    """The batch of a global step (samples and drawn targets) does not depend on the world size or the
    loader workers (sgmodel.data.loader docstring): 1, 2 and 4 ranks, 0 to 3 workers, 7 steps (2.3 epochs)."""
    one = global_batches(demo_dataset, 1, 0, 7)
    assert sorted(k for step in one[:3] for k, _ in step) == sorted(read_all(demo_dataset, "train"))
    for world, workers in [(2, 0), (4, 0), (1, 3), (2, 2), (4, 3)]:
        assert global_batches(demo_dataset, world, workers, 7) == one, (world, workers)
    assert global_batches(demo_dataset, 2, 2, 4, real_loader=True) == one[:4]  # spawned DataLoader workers


def test_workers_stopped_mid_stream_leave_without_aborting(demo_dataset):
    """A training loader dropped while its workers still send batches (the end of every run): no worker ends in
    SIGABRT. Python's finalization used to end the worker's queue feeder thread inside libtorch's tensor release
    (``loader._leave_at_exit``); on this CPU 9 of 80 worker exits of this loop aborted before, so 30 exits all
    ending well is the fix, not luck (0.89^30 = 3%)."""
    import subprocess
    import sys

    code = f"""
import gc
from pathlib import Path
from sgmodel.data.loader import make_loader
if __name__ == "__main__":
    for _ in range(15):
        batches = iter(make_loader(Path({str(demo_dataset)!r}), "train", 2, resolution=32, targets=4, seed=11,
                                   num_workers=2, rank=0, world_size=2, shuffle_buffer=3))
        for _ in range(4):
            next(batches)
        del batches
        gc.collect()
    print("ok")
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                         cwd=Path(__file__).resolve().parents[3])
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-2000:]
    assert "terminate called" not in run.stderr and "killed by signal" not in run.stderr, run.stderr[-2000:]


PROBE = """
import os, socket, sys, time
from multiprocessing import resource_sharer
from sgmodel.data.loader import init_loader_worker
if sys.argv[1] == "worker":
    init_loader_worker(0)
r, w = os.pipe()
handle = resource_sharer.DupFd(r)  # a handle offered to the command: the sharer's thread listens for it
s = socket.socket(socket.AF_UNIX)
s.connect(resource_sharer._resource_sharer._address)
s.close()  # hung up in the handshake, as a command stopped by Ctrl-C while it takes a batch's handle
time.sleep(0.5)
if sys.argv[2] == "raise":
    raise ValueError("an error of the worker's own")
print("done")
"""


@pytest.mark.parametrize("setup,then", [("plain", "end"), ("worker", "end"), ("worker", "raise")])
def test_a_hang_up_in_a_handles_hand_over_leaves_a_loader_worker_quiet(setup, then):
    """Ctrl-C of a command whose loader worker was handing it a batch's shared-memory handle: the handle-serving
    thread (``multiprocessing.resource_sharer``) printed the broken connection's traceback beside the command's one
    line (a CI run of tests/commands/test_interrupts.py saw it). ``init_loader_worker`` leaves it out; an ordinary
    process prints it (the case this guards against), and a worker's own errors are still printed."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", PROBE, setup, then], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[3])
    if setup == "plain":
        assert "resource_sharer.py" in run.stderr and "Traceback" in run.stderr, run.stderr
    elif then == "raise":  # printed whole, and nothing else
        assert run.stderr.startswith("Traceback") and run.stderr.endswith("ValueError: an error of the worker's own\n")
        assert "resource_sharer.py" not in run.stderr, run.stderr
    else:
        assert run.returncode == 0 and run.stdout.strip() == "done" and run.stderr == "", run.stderr


def test_training_resumes_on_another_number_of_ranks(demo_dataset):
    """A run stopped after step 4 on 2 ranks continues on 1 (and 4) with the batches the uninterrupted run
    would have seen."""
    full = global_batches(demo_dataset, 2, 0, 9)
    for world, workers in [(1, 0), (4, 2), (2, 1)]:
        assert global_batches(demo_dataset, world, workers, 5, start=4) == full[4:], (world, workers)


def test_iter_shard_reads_only_wanted_samples(demo_dataset, monkeypatch):
    """Unwanted samples of a shard are skipped by seeking: their bytes are never read."""
    shard = sorted((demo_dataset / "train").glob("shard-*.tar"))[0]
    full = list(iter_shard(shard))
    reads: list[int] = []
    real_open = open

    class Counting(io.FileIO):
        def read(self, n=-1):
            data = super().read(n)
            reads.append(len(data))
            return data

    monkeypatch.setattr(tarfile, "bltn_open", lambda name, mode="rb", *a, **k: Counting(name, mode)
                        if mode == "rb" else real_open(name, mode, *a, **k))
    part = list(iter_shard(shard, want=lambda i: i == 1))
    assert [k for k, _ in part] == [k for k, _ in full]
    assert part[1][1] == full[1][1] and all(m is None for i, (_, m) in enumerate(part) if i != 1)
    wanted_bytes = sum(len(v) for v in full[1][1].values())
    assert sum(reads) < wanted_bytes + 512 * (4 + sum(len(m) for _, m in full)), (sum(reads), wanted_bytes)
    assert sum(reads) < 0.6 * shard.stat().st_size


def test_loader_workers_share_the_hosts_cpus_among_its_ranks(monkeypatch):
    import os

    from sgmodel.data.loader import loader_workers

    monkeypatch.setattr(os, "sched_getaffinity", lambda _: set(range(64)))
    assert loader_workers(3, 4) == 3 and loader_workers(0, 4) == 0  # given: as given
    assert [loader_workers(None, ranks) for ranks in (1, 4, 8, 16)] == [8, 8, 7, 3]  # 64 CPUs: min(8, 64 / r - 1)
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: {0, 1})
    assert loader_workers(None, 1) == 1 and loader_workers(None, 4) == 1  # at least one
