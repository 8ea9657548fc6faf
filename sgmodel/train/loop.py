"""The training loop: validation (``validate``) and the loop (``train``) around the step (``sgmodel.train.step``);
what a run does and writes is the command's description (``sgmodel.train.command``)."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from scenesplat_stereo.common.commandline import Interrupted
from scenesplat_stereo.common.files import (append_line, atomic_write_bytes, read_json, read_json_lines,
                                            remove_temp_files)
from scenesplat_stereo.common.ownership import FolderLock, check_apart, check_replaceable
from scenesplat_stereo.common.text import format_table, value_cell
from sgmodel.config import ModelParams, TrainParams
from sgmodel.data.encoder_cache import EncoderCache, open_cache, precision_of
from sgmodel.data.loader import (RUN_SPLITS, check_first_sample, check_valid_pixels, load_sample, loader_workers,
                                 make_loader, read_split)
from sgmodel.metrics import image as metrics
from sgmodel.metrics.sheets import validation_sheet
from sgmodel.model.checkpoint import CheckpointError, load_checkpoint, load_weights, save_checkpoint
from sgmodel.model.layers import compiles
from sgmodel.model.network import StereoGaussians, create_model
from sgmodel.train.distributed import (World, all_sum, broadcast_flag, joined_world, same_on_every_rank,
                                       wrap_model)
from sgmodel.train.losses import create_objective
from sgmodel.train.step import (StepValues, TrainingDiverged, all_finite, create_optimizer, device_batch, no_mark,
                                queue_step, render_targets)
from sgmodel.train.step_profile import StepProfile, gathered_record

log = logging.getLogger(__name__)
OWNER = "sgmodel train"  # a run folder holds config.json; any other --out must be new or empty


@dataclass(frozen=True)
class RunPaths:
    """The files of one training run (see the module docstring)."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / "config.json"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.jsonl"

    @property
    def last(self) -> Path:
        return self.root / "checkpoints" / "last.pt"

    @property
    def best(self) -> Path:
        return self.root / "checkpoints" / "best.pt"

    def sheet(self, step: int) -> Path:
        return self.root / "sheets" / f"val_{step:06d}.png"


@torch.no_grad()
def validate(model, loader, world: World, amp: bool, sheet_samples: int, limit: int | None = None
             ) -> tuple[dict, list]:
    """Mean PSNR over every target of the split (full image and valid pixels only), summed over ranks;
    and the first ``sheet_samples`` samples of this rank for the contact sheet. ``limit`` caps the
    samples each rank validates on (None: all). A target whose mask has no valid pixel is left out of the
    valid-pixel mean and counted (``val_targets_without_valid_pixels``); that mean is None when no target has
    one."""
    was_training = model.training
    model.eval()
    total, total_masked, count, count_masked, shown = 0.0, 0.0, 0, 0, []
    samples = 0
    for batch in loader:
        if limit is not None and samples >= limit:
            break
        samples += len(batch["keys"])
        batch = device_batch(batch, world.device)
        rgb, _, pred = render_targets(model, batch, amp)
        total += metrics.psnr(rgb, batch["targets"]).sum().item()
        defined = metrics.has_valid_pixel(batch["masks"])  # the others' masked PSNR is NaN
        total_masked += metrics.psnr(rgb, batch["targets"], batch["masks"])[defined].sum().item()
        count += rgb.shape[0] * rgb.shape[1]
        count_masked += int(defined.sum().item())
        for i in range(rgb.shape[0]):
            if len(shown) < sheet_samples:
                shown.append({"left": batch["left"][i], "depth": pred.depth[i], "targets": batch["targets"][i],
                              "renders": rgb[i], "key": batch["keys"][i]})
    model.train(was_training)
    total, total_masked, count, count_masked = all_sum(world, [total, total_masked, float(count), float(count_masked)])
    if count == 0:
        raise ValueError("the validation split has no targets")
    return {"val_psnr": total / count, "val_psnr_masked": total_masked / count_masked if count_masked else None,
            "val_targets": int(count), "val_targets_without_valid_pixels": int(count - count_masked)}, shown


def mean_over_ranks(world: World, stats: dict) -> dict:
    """The step's loss, its parts and PSNR averaged over ranks (each rank measured its share of the global
    batch, all shares the same size), so a record means the same on any number of GPUs; lr as it is."""
    keys = [k for k in stats if k != "lr"]
    return {**stats, **dict(zip(keys, (v / world.size for v in all_sum(world, [stats[k] for k in keys]))))}


def _trim_metrics(path: Path, step: int | None) -> None:
    """On resume at ``step``, drop records written after it (they will be written again), and a torn last
    line (with a warning); a new run (``step`` None) starts the file afresh."""
    if not path.exists():
        return
    if step is None:
        path.unlink()
        return
    keep = [json.dumps(r) for r in read_json_lines(path) if r.get("step", 0) <= step]
    atomic_write_bytes(path, "".join(line + "\n" for line in keep).encode())


def run_config(model_params: ModelParams, train_params: TrainParams, data: Path, encoder, objective,
               init_from: dict | None = None, cache: EncoderCache | None = None) -> dict:
    """The record written to RUN/config.json; a resumed run must match it (except the worker count and the
    encoder cache, which changes no number)."""
    return {"model": model_params.to_dict(), "train": train_params.to_dict(), "data": str(Path(data).resolve()),
            "encoder": {"name": encoder.name, "weights_sha256": encoder.weights_sha256},
            "loss": objective.to_config(), "init_from": init_from,
            "encoder_cache": str(cache.root.resolve()) if cache is not None else None}


def open_run_cache(path: Path, data: Path, encoder, resolution: int, device: str | torch.device, amp: bool
                   ) -> EncoderCache:
    """The encoder cache at ``path`` checked for a training run (both splits, the run's encoder, resolution
    and precision): ``encoder_cache.open_cache``."""
    return open_cache(path, data, encoder, resolution, precision_of(device, amp), list(RUN_SPLITS))


def check_run_folder(paths: RunPaths, data: Path) -> None:
    """``--out`` can hold a run: a folder (or creatable), writable, not inside ``--data``, and either free
    of other files or a run (config.json; ``common.ownership.check_replaceable``, the one owner). Reads only."""
    check_replaceable(paths.root, "--out", OWNER, marker=paths.config.name)
    check_apart(paths.root, "--out", {"--data": data})


def _check_resumable(paths: RunPaths, config: dict) -> bool:
    """True to resume from last.pt; False for a new run; ValueError when RUN holds a run of other settings
    that saved a checkpoint (a run without one is started afresh, with a warning)."""
    if not paths.config.exists():
        return False
    old, config = read_json(paths.config), json.loads(json.dumps(config))  # as JSON sees it
    if not isinstance(old, dict):
        raise ValueError(f"{paths.config}: not a JSON object; choose another --out")
    differs = [part for part in ("model", "data", "encoder", "loss", "init_from") if old.get(part) != config[part]]
    # workers do not change results, compilation and shares only their rounding, as another number of ranks
    # does (and a run from before a compile flag existed, or from when the composer was compiled, resumes)
    ignore = ("workers", "compile_lpips", "compile_composer", "ddp_bucket_mb", "profile", "accumulate")
    if {k: v for k, v in old.get("train", {}).items() if k not in ignore} != \
            {k: v for k, v in config["train"].items() if k not in ignore}:
        differs.append("train")
    if differs and paths.last.exists():
        raise ValueError(f"--out {paths.root}: holds a run trained with other settings ({', '.join(differs)} "
                         f"differ); rerun with its flags to resume it, or choose a new --out (add --init-from "
                         f"{paths.last} to start from its weights)")
    if differs:
        log.warning(f"--out {paths.root}: an earlier attempt with other settings saved no checkpoint; starting "
                    f"afresh with these settings")
        return False
    return paths.last.exists()


def _init_from(path: Path | None, model: StereoGaussians) -> dict | None:
    """Load ``--init-from``'s weights into ``model`` (CheckpointError naming the flag and file when they do not
    fit); the record kept in config.json."""
    if path is None:
        return None
    try:
        ckpt = load_checkpoint(path)
    except CheckpointError as e:
        raise CheckpointError(f"--init-from {e}") from None
    load_weights(model, ckpt, f"--init-from {path}")
    theirs = ckpt.get("encoder", {}) or {}
    if theirs.get("name") not in (None, model.encoder.name):
        log.warning(f"--init-from {path}: trained with encoder {theirs.get('name')!r}, this run uses "
                    f"{model.encoder.name!r}")
    return {"checkpoint": str(Path(path).resolve()), "step": ckpt["step"]}


def train(model_params: ModelParams, train_params: TrainParams, data: Path, out: Path, device: str = "cpu",
          vgg_path: str | None = None, progress: bool = True, init_from: Path | None = None,
          encoder_cache: Path | None = None) -> dict:
    """Train (or resume) a run in ``out``; returns the summary (steps, best validation PSNR, wall time).
    ``init_from``: a checkpoint whose weights start a new run (its optimiser, schedule and step are not
    taken). ``encoder_cache``: a cache of the encoder's outputs on ``data`` (``sgmodel encode``), read in
    place of running the encoder (the same numbers; it may be given or left out when a run resumes)."""
    model_params.validate()
    train_params.validate()
    with joined_world(device) as world:
        return _train(model_params, train_params, Path(data), RunPaths(Path(out)), world, vgg_path, progress,
                      init_from, encoder_cache)


def _train(model_params: ModelParams, tp: TrainParams, data: Path, paths: RunPaths, world: World,
           vgg_path: str | None, progress: bool, init_from: Path | None, encoder_cache: Path | None) -> dict:
    if tp.batch_size % world.size:
        raise ValueError(f"--batch-size {tp.batch_size} must be divisible by the {world.size} ranks")
    if (tp.batch_size // world.size) % tp.accumulate:
        raise ValueError(f"--accumulate {tp.accumulate}: must divide the batch per rank ({tp.batch_size // world.size}"
                         f" = --batch-size {tp.batch_size} over {world.size} rank(s))")
    if tp.ddp_bf16_grads and world.device.type != "cuda":
        raise ValueError("--ddp-bf16-grads: the bfloat16 all-reduce needs NCCL (CUDA devices)")
    check_run_folder(paths, data)
    read_split_checked(data, model_params.resolution, tp.targets)
    torch.manual_seed(tp.seed)
    # every training step has the same shapes: let cuDNN time its algorithms once (8% of a step on an H100)
    torch.backends.cudnn.benchmark = world.device.type == "cuda"
    model = create_model(model_params, world.device)
    objective = create_objective(vgg_path, device=world.device, weight=tp.lpips_weight, amp=tp.amp,
                                 compile_trunk=compiles(world.device, tp.compile_lpips))
    cache = open_run_cache(encoder_cache, data, model.encoder, model_params.resolution, world.device, tp.amp) \
        if encoder_cache is not None else None
    config = run_config(model_params, tp, data, model.encoder, objective, _init_from(init_from, model), cache)
    lock = FolderLock(paths.root, "--out", OWNER)
    if world.main:
        lock.acquire()  # the first write: RUN and its .lock (both undone if what follows refuses the run)
    try:
        return _run(model, objective, config, model_params, tp, data, paths, world, progress, cache)
    finally:
        lock.release()


def _resume_state(paths: RunPaths, config: dict, model, optimizer, scheduler, world: World) -> tuple:
    """(step, best PSNR, best step, resumed) to start from: last.pt's, loaded into the model, the optimiser,
    the scheduler and the RNG; or a new run's. CheckpointError naming last.pt when it does not fit."""
    if not _check_resumable(paths, config):
        return 0, float("-inf"), None, False
    ckpt = load_checkpoint(paths.last, map_location=world.device)
    load_weights(model, ckpt, paths.last)
    try:
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        torch.set_rng_state(ckpt["rng"]["torch"].cpu())
        if world.device.type == "cuda" and ckpt["rng"].get("cuda") is not None:
            torch.cuda.set_rng_state(ckpt["rng"]["cuda"].cpu(), world.device)
        return ckpt["step"], ckpt["best_val_psnr"], ckpt["best_step"], True
    except (KeyError, ValueError, RuntimeError, TypeError) as e:
        raise CheckpointError(f"{paths.last}: its optimiser, schedule or RNG state does not fit this run "
                              f"({type(e).__name__}: {e})") from None


def _run(model, objective, config: dict, model_params: ModelParams, tp: TrainParams, data: Path, paths: RunPaths,
         world: World, progress: bool, cache: EncoderCache | None) -> dict:
    local_batch, S = tp.batch_size // world.size, model_params.resolution
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = create_optimizer(params, world.device, lr=tp.lr, betas=tp.betas, weight_decay=tp.weight_decay)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=tp.lr, total_steps=tp.steps,
                                                    pct_start=tp.warmup, div_factor=tp.div_factor,
                                                    final_div_factor=tp.final_div_factor)
    step, best, best_step, resume = _resume_state(paths, config, model, optimizer, scheduler, world)
    if not same_on_every_rank(world, step):
        raise ValueError(f"--out {paths.root}: the ranks resume from different steps (this rank {world.rank}: "
                         f"{step}); on several hosts RUN must be one shared folder, or hold the same "
                         f"config.json and checkpoints/last.pt on every host")
    pinned = world.device.type == "cuda"  # page-locked batches: the copy to the GPU does not block the host
    workers = loader_workers(tp.workers, world.local_size)
    train_loader = make_loader(data, "train", local_batch, S, tp.targets, tp.seed, workers, world.rank,
                               world.size, train=True, start_step=step, cache=cache, pin_memory=pinned)
    val_loader = make_loader(data, "val", local_batch, S, None, tp.seed, workers, world.rank, world.size,
                             train=False, cache=cache, pin_memory=pinned)
    if world.main:
        print(f"sgmodel train: {'resuming at step ' + str(step) if resume else 'new run'} in {paths.root}; "
              f"loss {objective.description}; encoder {model.encoder.name}"
              f"{' (its outputs from ' + str(cache.root) + ')' if cache is not None else ''}; {world.size} rank(s) on "
              f"{world.device}; batch {tp.batch_size} ({local_batch} per rank) at {S}x{S}", flush=True)
        remove_temp_files(paths.root)  # of a killed run's unfinished writes (we hold the lock)
        atomic_write_bytes(paths.config, (json.dumps(config, indent=2) + "\n").encode())
        _trim_metrics(paths.metrics, step if resume else None)
    net = wrap_model(model, world, tp.ddp_bucket_mb, tp.ddp_bf16_grads)
    net.train()
    profile = StepProfile(model, params, world.device) if tp.profile else None
    t_start = time.perf_counter()
    bar = tqdm(total=tp.steps, initial=step, disable=not (progress and world.main), unit="step", dynamic_ncols=True)
    saved = step if resume else None  # the step last.pt holds
    first_shown: dict = {}  # the renders of this process's first validation (step 0 of a new run)

    def validation(step: int, best: float) -> tuple[bool, float, float]:
        """Validate (each rank its share), log, draw the sheet; (is it the best so far, its PSNR, when rank 0
        began writing). Step 0 is never the best. With ``--profile`` the record also holds each rank's
        validation time (``val_ms``)."""
        t0 = time.perf_counter()
        val, shown = validate(net, val_loader, world, tp.amp, tp.sheet_samples, tp.val_samples)
        if profile is not None:
            val.update(gathered_record(world, {"val_ms": (time.perf_counter() - t0) * 1e3}))
        improved = broadcast_flag(world, step > 0 and val["val_psnr"] > best)
        for sample in shown:
            sample["step"] = step
        if not first_shown and shown:  # the sheets show this first validation's renders beside each later one
            first_shown.update(step=step, renders=[sample["renders"] for sample in shown])
        t_write = time.perf_counter()
        if world.main:
            bar.write(f"step {step}: val PSNR {val['val_psnr']:.2f} dB (valid pixels {valid_pixel_psnr(val, True)})"
                      f"{' best' if improved else ''}")
            append_line(paths.metrics, json.dumps({"step": step, **val}))
            atomic_write_bytes(paths.sheet(step), validation_sheet(shown, first_shown or None))
        return improved, val["val_psnr"], t_write

    def diverged(at: int, what: str) -> TrainingDiverged:
        held = f"{paths.last} holds step {saved}" if saved is not None else "no checkpoint was written before it"
        go_on = (f"start a new run from its last checkpoint: --init-from {paths.last} --out NEW_RUN"
                 if saved is not None else f"rerun in the same --out {paths.root}")
        return TrainingDiverged(f"training diverged at step {at}: {what}; nothing of it was saved ({held}). To go "
                                f"on with other settings (a lower --lr, say {tp.lr / 2:g}), {go_on}", at,
                                paths.last if saved is not None else None, saved, tp.lr)

    grads_finite = torch.ones((), dtype=torch.bool, device=world.device)
    try:
        if step == 0:  # where training starts from, for the PSNR curve
            validation(0, best)
        batches = iter(train_loader)
        queued = None  # (step, StepValues) of the last step queued, its values not read yet
        since = 0.0  # when the step before the one read next ended on the host (its values read), or began

        def read_values(at: int, values: StepValues) -> tuple[dict, float]:
            """The values of step ``at`` and the ms since the step before's (the step's time: its start when
            nothing was in flight); the progress bar moved on."""
            nonlocal since
            try:
                stats = values.read()
            except TrainingDiverged as e:
                raise diverged(at, str(e)) from None
            now = time.perf_counter()
            ms, since = (now - since) * 1e3, now
            bar.update(1)
            bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}", ms=f"{ms:.0f}")
            return stats, ms

        while step < tp.steps:
            t0 = time.perf_counter()
            if queued is None:
                since = t0
            batch = device_batch(next(batches), world.device)
            if profile is not None:
                data_ms = (time.perf_counter() - t0) * 1e3
                profile.begin()
            try:
                values = queue_step(net, batch, objective, optimizer, scheduler, tp.amp,
                                    profile.mark if profile is not None else no_mark, tp.accumulate)
            except TrainingDiverged as e:
                raise diverged(step + 1, str(e)) from None
            step += 1
            grads_finite &= all_finite([p.grad for p in params if p.grad is not None])
            if queued is not None:  # the step before, read while this one runs on the device
                read_values(*queued)
            logged = step % tp.log_every == 0 or step == tp.steps
            checkpoint = step % tp.val_every == 0 or step == tp.steps
            if not (logged or checkpoint):
                queued = (step, values)
                continue
            queued = None
            stats, ms = read_values(step, values)
            # one sync for both flags, where the step's values were read anyway
            grads_ok, weights_ok = torch.stack([grads_finite, all_finite(params)]).tolist()
            if not (grads_ok and weights_ok):
                raise diverged(step, "a gradient is NaN or infinite" if not grads_ok else
                               "a weight is NaN or infinite")
            if logged:
                if profile is None:
                    stats = mean_over_ranks(world, stats)
                else:  # every rank's phases of this step, in the collective that averages the loss
                    means = {k: v for k, v in stats.items() if k != "lr"}
                    stats = {**stats, **gathered_record(world, profile.phases(data_ms, batch), means)}
                if world.main:
                    append_line(paths.metrics, json.dumps({"step": step, **stats, "step_ms": ms}))
            if checkpoint:
                improved, psnr, t_write = validation(step, best)
                if improved:
                    best, best_step = psnr, step
                if world.main:  # the other ranks go on and wait for rank 0 in the next step's all-reduce
                    state = _state(model, config, optimizer, scheduler, step, best, best_step, world)
                    save_checkpoint(paths.last, state)
                    if improved:
                        save_checkpoint(paths.best, state)
                    if profile is not None:
                        append_line(paths.metrics, json.dumps(
                            {"step": step, "write_ms": (time.perf_counter() - t_write) * 1e3}))
                saved = step
    except KeyboardInterrupt:
        bar.close()
        kept = f"{paths.last} holds step {saved}" if saved is not None else "no checkpoint was written yet"
        raise Interrupted(f"at step {step}; {kept}: rerun the same command to "
                          f"{'resume' if saved is not None else 'start again'}") from None
    bar.close()
    summary = {"steps": step, "best_val_psnr": best, "best_step": best_step,
               "wall_s": time.perf_counter() - t_start, "run": str(paths.root)}
    if world.main:
        print(summary_table(paths.metrics, summary), flush=True)
    return summary


def _state(model, config, optimizer, scheduler, step, best, best_step, world: World) -> dict:
    rng = {"torch": torch.get_rng_state(),
           "cuda": torch.cuda.get_rng_state(world.device) if world.device.type == "cuda" else None}
    return {"model_params": config["model"], "train_params": config["train"], "encoder": config["encoder"],
            "loss": config["loss"], "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(), "step": step, "best_val_psnr": best, "best_step": best_step,
            "rng": rng}


def summary_table(metrics_path: Path, summary: dict) -> str:
    """The validation history as a text table, then the best step."""
    rows = [r for r in read_json_lines(metrics_path) if "val_psnr" in r]
    table = format_table([["step", "val PSNR (dB)", "valid-pixel PSNR (dB)", "targets"]] +
                         [[r["step"], f"{r['val_psnr']:.2f}", valid_pixel_psnr(r), r["val_targets"]]
                          for r in rows], rule=True)
    last = rows[-1] if rows else {}
    if last.get("val_targets_without_valid_pixels"):
        table += (f"\n{last['val_targets_without_valid_pixels']} of {last['val_targets']} validation targets have no "
                  f"valid pixel: left out of the valid-pixel PSNR")
    return (f"{table}\nbest validation PSNR {summary['best_val_psnr']:.2f} dB at step {summary['best_step']}; "
            f"{summary['steps']} steps in {summary['wall_s']:.0f} s; checkpoints in {summary['run']}/checkpoints")


def valid_pixel_psnr(record: dict, left_out: bool = False) -> str:
    """A validation record's valid-pixel PSNR as text, in dB ("n/a" when no target had a valid pixel);
    ``left_out``: and how many targets it leaves out (those without a valid pixel), if any."""
    value, without = record["val_psnr_masked"], record.get("val_targets_without_valid_pixels", 0)
    text = value_cell(value, 2)
    return f"{text}; {without} of {record['val_targets']} targets without any, left out" if left_out and without \
        else text


def read_split_checked(data: Path, resolution: int, targets: int) -> None:
    """Both splits a run needs exist, list readable shards, their first samples decode at ``resolution`` with
    ``targets`` training targets, and some target of each has a valid pixel (``check_valid_pixels``). DataError
    naming the file or split (and the flag) otherwise. Reads only."""
    for split in RUN_SPLITS:
        check_first_sample(read_split(Path(data), split), lambda key, members, source, split=split: load_sample(
            key, members, source, resolution, targets if split == "train" else None))
        check_valid_pixels(Path(data), split)
