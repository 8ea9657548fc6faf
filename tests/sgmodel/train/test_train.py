"""Training: the step function overfits, a short run learns, an interrupted run resumes exactly, and bad
input is refused before anything is written."""

from __future__ import annotations

import copy
import json
import re

import numpy as np
import pytest
import torch

from sgmodel.cli import main as sgmodel_main
from sgmodel.config import DecoderParams, ModelParams, PredictorParams, TrainParams
from sgmodel.model.network import create_model
from sgmodel.train import loop as train_mod
from sgmodel.train import step as step_mod
from sgmodel.train.distributed import World
from sgmodel.train.losses import create_objective
from tests.support.model_helpers import StandInEncoder, textured_batch


def tiny_model_params() -> ModelParams:
    p = ModelParams(resolution=32, padding=2, decoder=DecoderParams(channels=16, groups=4),
                    predictor=PredictorParams(channels=16, groups=4))
    p.encoder.name = "sgbm"
    return p


def tiny_schedule(**changes) -> TrainParams:
    t = TrainParams(steps=12, batch_size=2, targets=2, val_every=6, log_every=2, workers=0, lr=2e-3, amp=False,
                    sheet_samples=2)
    for k, v in changes.items():
        setattr(t, k, v)
    return t


def test_overfitting_one_batch_raises_psnr_by_10db():
    torch.manual_seed(0)
    batch = textured_batch(B=2, T=2, S=32)
    batch["targets"] = 1.0 - batch["targets"]  # colours the initial Gaussians do not have
    model = create_model(ModelParams(resolution=32, padding=2, decoder=DecoderParams(channels=16, groups=4),
                                     predictor=PredictorParams(channels=16, groups=4)), encoder=StandInEncoder())
    objective = create_objective(None, device="cpu")
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=3e-3)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda _: 1.0)
    first = step_mod.train_step(model, batch, objective, opt, sched, amp=False)["psnr"]
    for _ in range(150):
        last = step_mod.train_step(model, batch, objective, opt, sched, amp=False)["psnr"]
    assert last >= first + 10.0, (first, last)


@pytest.mark.parametrize("fused", [True, False])
def test_a_non_finite_loss_changes_no_weight_with_a_fused_or_a_plain_optimiser(fused):
    """``skip_unless_finite``: a fused AdamW (as on CUDA; fused runs on the CPU too) is told by ``found_inf`` to
    leave weights, moments and step counts as they were, a plain one is never stepped; either way the step
    raises ``TrainingDiverged`` naming the loss, and the next finite step updates as usual."""
    torch.manual_seed(0)
    batch = textured_batch(B=2, T=2, S=32)
    model = create_model(tiny_model_params(), encoder=StandInEncoder())
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=1e-3, fused=fused)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda _: 1.0)
    objective = create_objective(None, device="cpu")
    step_mod.train_step(model, batch, objective, opt, sched, amp=False)  # the moments exist and are not zero

    def held():
        return [t.clone() for p in params for t in (p.detach(), *opt.state[p].values())]

    before = held()
    def nan(render, target):
        loss, parts = objective(render, target)
        return loss * float("nan"), parts

    with pytest.raises(step_mod.TrainingDiverged, match="the loss is nan"):
        step_mod.train_step(model, batch, nan, opt, sched, amp=False)
    assert all(torch.equal(a, b) for a, b in zip(before, held()))
    assert getattr(opt, "found_inf", None) is None or opt.found_inf.item() == 1.0
    step_mod.train_step(model, batch, objective, opt, sched, amp=False)
    after = held()
    assert not torch.equal(before[0], after[0]) and opt.state[params[0]]["step"].item() == 2


def test_a_step_in_shares_is_the_step_on_the_whole_batch():
    """``train_step(accumulate=N)``: N shares' losses, each over its pairs, averaged, the weights after the step
    and the logged values those of the whole batch (float32 summation order apart); the same shares cut
    from each batched tensor and list, encoder features included (``batch_share``)."""
    from sgmodel.data.loader import batch_share

    torch.manual_seed(0)
    batch = textured_batch(B=4, T=2, S=32)
    batch["encoder_features"] = [torch.arange(4.0).view(4, 1).expand(4, 3), torch.arange(4.0).view(4, 1, 1)]
    half = batch_share(batch, 1, 2)
    assert half["keys"] == ["s2", "s3"] and torch.equal(half["left"], batch["left"][2:])
    assert [f.flatten().unique().tolist() for f in half["encoder_features"]] == [[2.0, 3.0], [2.0, 3.0]]
    with pytest.raises(ValueError, match="4 pairs does not split into 3"):
        batch_share(batch, 0, 3)
    del batch["encoder_features"]
    model0 = create_model(tiny_model_params(), encoder=StandInEncoder())
    objective = create_objective(None, device="cpu")
    runs = []
    for shares in (1, 2, 4):
        model = copy.deepcopy(model0)
        # SGD, not AdamW: its step is proportional to the gradient, so a sum of shares not divided is seen
        opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=1e-2)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda _: 1.0)
        stats = step_mod.train_step(model, batch, objective, opt, sched, amp=False, accumulate=shares)
        runs.append((stats, torch.cat([p.detach().flatten() for p in model.parameters()])))
    moved = (runs[0][1] - torch.cat([p.detach().flatten() for p in model0.parameters()])).norm()
    for stats, weights in runs[1:]:
        # measured 7e-7 and 1.3e-6 of the step (float32 summation order); shares summed, not averaged: 1
        assert (weights - runs[0][1]).norm() < 1e-4 * moved
        assert stats["loss"] == pytest.approx(runs[0][0]["loss"], rel=1e-5)
        assert stats.keys() == runs[0][0].keys()


def _records(run):
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_validation_leaves_out_and_counts_targets_without_a_valid_pixel(monkeypatch):
    """One target, then a whole sample, without a valid pixel: the valid-pixel PSNR is the mean over the other
    targets (computed here from its definition), never NaN; None when no target has a valid pixel."""
    batches = [textured_batch(B=2, T=2, S=32, seed=s) for s in (0, 1)]
    batches[0]["masks"][0, 0, :, :16] = False  # half the pixels
    batches[0]["masks"][0, 1] = False  # a target without a valid pixel
    batches[1]["masks"][1] = False  # a sample without one
    monkeypatch.setattr(train_mod, "render_targets", lambda model, batch, amp: (batch["targets"].flip(-1), None, None))
    world = World(rank=0, size=1, device=torch.device("cpu"))
    val, _ = train_mod.validate(torch.nn.Identity(), batches, world, amp=False, sheet_samples=0)
    want = []
    for b in batches:
        for i in range(2):
            for t in range(2):
                m = b["masks"][i, t, 0].numpy()
                if m.any():
                    err = (b["targets"][i, t].flip(-1) - b["targets"][i, t]).numpy()[:, m]
                    want.append(10 * np.log10(1 / (err.astype(np.float64) ** 2).mean()))
    assert len(want) == 5 and val["val_targets"] == 8 and val["val_targets_without_valid_pixels"] == 3
    assert val["val_psnr_masked"] == pytest.approx(np.mean(want), abs=1e-4) and np.isfinite(val["val_psnr"])
    for b in batches:
        b["masks"][:] = False
    val, _ = train_mod.validate(torch.nn.Identity(), batches, world, amp=False, sheet_samples=0)
    assert val["val_psnr_masked"] is None and val["val_targets_without_valid_pixels"] == 8
    assert train_mod.valid_pixel_psnr(val, left_out=True) == "n/a; 8 of 8 targets without any, left out"


def test_short_run_raises_validation_psnr_and_writes_its_files(demo_dataset, tmp_path):
    run = tmp_path / "run"
    summary = train_mod.train(tiny_model_params(), tiny_schedule(steps=30, val_every=15, lr=4e-3), demo_dataset, run,
                              progress=False)
    vals = [r for r in _records(run) if "val_psnr" in r]
    assert [r["step"] for r in vals] == [0, 15, 30]
    assert vals[-1]["val_psnr"] > vals[0]["val_psnr"], vals
    assert summary["best_step"] in (15, 30)
    config = json.loads((run / "config.json").read_text())
    assert config["encoder"]["name"] == "sgbm" and config["loss"]["name"] == "mse+ssim"
    for name in ("checkpoints/last.pt", "checkpoints/best.pt", "sheets/val_000015.png"):
        assert (run / name).is_file(), name
    ckpt = torch.load(run / "checkpoints/last.pt", weights_only=True)
    assert not any("encoder" in k for k in ckpt["model"]) and ckpt["step"] == 30


def test_resume_gives_the_same_weights(demo_dataset, tmp_path, monkeypatch):
    params, schedule = tiny_model_params(), tiny_schedule()
    train_mod.train(params, schedule, demo_dataset, tmp_path / "a", progress=False)

    real_step, calls = train_mod.queue_step, {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 9:  # after the checkpoint at step 6
            raise KeyboardInterrupt
        return real_step(*args, **kwargs)

    monkeypatch.setattr(train_mod, "queue_step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_mod.train(params, schedule, demo_dataset, tmp_path / "b", progress=False)
    monkeypatch.setattr(train_mod, "queue_step", real_step)
    assert torch.load(tmp_path / "b/checkpoints/last.pt", weights_only=True)["step"] == 6
    train_mod.train(params, schedule, demo_dataset, tmp_path / "b", progress=False)
    a = torch.load(tmp_path / "a/checkpoints/last.pt", weights_only=True)
    b = torch.load(tmp_path / "b/checkpoints/last.pt", weights_only=True)
    assert a["step"] == b["step"] == 12
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    timeless = [[{k: v for k, v in r.items() if k != "step_ms"} for r in _records(tmp_path / x)] for x in "ab"]
    assert timeless[0] == timeless[1]  # the resumed run logged the same steps, losses and validations


def test_each_steps_values_are_read_once_the_next_is_queued_and_at_once_where_logged(demo_dataset, tmp_path,
                                                                                     monkeypatch):
    """The loop never waits for a step's values before the next step is queued, except at a logged or
    validated step (whose record and checkpoint need them); every step is read once, in order."""
    order, real_queue, real_read = [], train_mod.queue_step, step_mod.StepValues.read

    def queue(*args, **kwargs):
        values = real_queue(*args, **kwargs)
        values.number = sum(1 for what, _ in order if what == "queued") + 1
        order.append(("queued", values.number))
        return values

    def read(self):
        order.append(("read", self.number))
        return real_read(self)

    monkeypatch.setattr(train_mod, "queue_step", queue)
    monkeypatch.setattr(step_mod.StepValues, "read", read)
    train_mod.train(tiny_model_params(), tiny_schedule(steps=7, log_every=3, val_every=6), demo_dataset,
                    tmp_path / "r", progress=False)
    q, r = (lambda n: ("queued", n)), (lambda n: ("read", n))
    assert order == [q(1), q(2), r(1), q(3), r(2), r(3), q(4), q(5), r(4), q(6), r(5), r(6), q(7), r(7)]


def test_the_model_does_not_check_a_batch_the_loop_checked_on_the_host(demo_dataset, tmp_path, monkeypatch):
    """``device_batch`` checks K and the baseline where the loader made them (no read back from a GPU); the
    model is told and does not check them again. A bad batch is refused there, naming its items."""
    checked = []
    monkeypatch.setattr(step_mod, "check_inputs", lambda *a: checked.append(a[2].device.type))
    monkeypatch.setattr("sgmodel.model.network.check_inputs", lambda *a: pytest.fail("the model checked again"))
    train_mod.train(tiny_model_params(), tiny_schedule(steps=2, val_every=2), demo_dataset, tmp_path / "r",
                    progress=False)
    assert checked and set(checked) == {"cpu"}  # the training batches and the validation's
    monkeypatch.undo()
    batch = textured_batch(B=3, T=1, S=32)
    batch["K"][1, 0, 0] = float("nan")
    batch["baseline"][2] = 0.0
    with pytest.raises(ValueError, match=r"K must be finite.*batch items \[1\]"):
        step_mod.device_batch(batch, torch.device("cpu"))
    batch["K"][1, 0, 0] = 30.0
    with pytest.raises(ValueError, match=r"baseline must be finite and > 0 metres: not so for batch items \[2\]"):
        step_mod.device_batch(batch, torch.device("cpu"))
    batch["baseline"][2] = 0.1
    assert step_mod.device_batch(batch, torch.device("cpu"))["inputs_checked"] is True


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the side stream of device_batch needs a CUDA device")
def test_a_batch_copied_on_the_side_stream_is_what_the_current_stream_reads():
    """The copy runs on ``device_batch``'s side stream; the current stream waits for it: held back on purpose
    (the side stream asleep before the copy), the values read on the current stream are still the batch's."""
    device = torch.device("cuda")
    batch = textured_batch(B=4, T=2, S=64)
    host = {k: v.contiguous().pin_memory() if torch.is_tensor(v) else v for k, v in batch.items()}
    step_mod.device_batch(host, device)  # the side stream exists from now on
    torch.cuda.synchronize()
    stream = step_mod._copy_streams[torch.device("cuda", torch.cuda.current_device())]
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        torch.cuda._sleep(200_000_000)  # about 0.1 s: the copy queued behind it
    moved = step_mod.device_batch(host, device)
    for k, v in batch.items():
        if torch.is_tensor(v):
            assert moved[k].device.type == "cuda" and torch.equal(moved[k].cpu(), v), k
    assert moved["inputs_checked"] is True and moved["keys"] == batch["keys"]


def test_step_values_read_as_numbers_and_a_non_finite_loss_raises():
    values = step_mod.StepValues(torch.tensor([0.5, 21.0, 0.25]), ["mse"], 1e-3)
    assert values.read() == {"loss": 0.5, "psnr": 21.0, "lr": 1e-3, "mse": 0.25}
    with pytest.raises(step_mod.TrainingDiverged, match="the loss is inf"):
        step_mod.StepValues(torch.tensor([float("inf"), 21.0]), [], 1e-3).read()


def test_resume_refuses_other_settings(demo_dataset, tmp_path):
    train_mod.train(tiny_model_params(), tiny_schedule(steps=6), demo_dataset, tmp_path / "r", progress=False)
    before = (tmp_path / "r/config.json").read_bytes()
    with pytest.raises(ValueError, match="other settings"):
        train_mod.train(tiny_model_params(), tiny_schedule(steps=6, lr=1e-3), demo_dataset, tmp_path / "r",
                        progress=False)
    assert (tmp_path / "r/config.json").read_bytes() == before


@pytest.mark.parametrize("argv,match", [
    (["--data", "{missing}"], "missing|no such|not found|does not exist"),
    (["--steps", "0"], "--steps"),
    (["--resolution", "30"], "resolution"),
    (["--encoder", "nope"], "nope"),
    (["--device", "tpu"], "--device"),
])
def test_cli_bad_input_exits_2_and_writes_nothing(demo_dataset, tmp_path, capsys, argv, match):
    out = tmp_path / "run"
    args = ["train", "--data", str(demo_dataset), "--out", str(out), "--preset", "cpu-small", "--steps", "2",
            "--no-progress"]
    args += [a.format(missing=tmp_path / "nothing-here") for a in argv]
    try:
        code = sgmodel_main(args)
    except SystemExit as e:  # argparse's own refusals
        code = e.code
    assert code == 2
    assert re.search(match, capsys.readouterr().err)
    assert not out.exists()


def test_torchrun_two_ranks_split_the_batch_and_only_rank_0_writes(demo_dataset, tmp_path):
    """DDP on the CPU (gloo): two processes, batch 4 split 2 + 2; validation sums both ranks' targets."""
    import subprocess
    import sys

    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone", "-m",
           "sgmodel.cli", "train", "--data", str(demo_dataset), "--out", str(run), "--device", "cpu",
           "--preset", "cpu-small", "--resolution", "32", "--padding", "2", "--batch-size", "4", "--steps", "2",
           "--val-every", "2", "--workers", "0", "--no-progress"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("sgmodel train: new run") == 1  # rank 0 alone speaks
    assert "2 rank(s)" in done.stdout and "(2 per rank)" in done.stdout
    vals = [r for r in _records(run) if "val_psnr" in r]
    assert [r["step"] for r in vals] == [0, 2] and all(r["val_targets"] == 20 for r in vals)
    assert (run / "checkpoints/best.pt").is_file()
