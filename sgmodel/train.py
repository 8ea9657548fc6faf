"""Training: a step function (``train_step``), validation (``validate``) and the loop (``train``).

The loop reads shards through ``sgmodel.data``, predicts Gaussians with the model, renders every target
through ``sgmodel.render`` (our Warp rasteriser and its hand-written backward), and minimises
MSE + 0.05 LPIPS-VGG (or MSE + 0.05 (1 - SSIM) without the VGG weights) with AdamW and OneCycleLR
(SPEC section 7). Every ``val_every`` steps it validates on the whole validation split, writes a contact
sheet (input, depth, targets, renders) and keeps the checkpoint with the highest validation PSNR.

Files in RUN (only rank 0 writes, every file atomically): ``config.json`` (all settings, the encoder and
its weights hash, the loss used), ``metrics.jsonl`` (one record per ``log_every`` steps: step, loss, psnr,
lr, step_ms; one per validation: step, val_psnr, val_psnr_masked, val_targets), ``checkpoints/last.pt``
and ``best.pt`` (``sgmodel.checkpoint``), ``sheets/val_<step>.png``. An interrupted run resumes from
``last.pt`` exactly: weights, optimiser, scheduler, RNG and the data order (a function of seed and step).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from scenesplat_stereo.files import atomic_write_bytes
from scenesplat_stereo.text import format_table

from . import metrics
from .checkpoint import load_checkpoint, save_checkpoint
from .config import ModelParams, TrainParams
from .data import make_loader, read_split
from .distributed import World, all_sum, broadcast_flag, close_world, init_world
from .losses import create_objective
from .model import StereoGaussians, create_model
from .render import render_views
from .sheets import validation_sheet


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


def render_targets(model: StereoGaussians | DistributedDataParallel, batch: dict, amp: bool):
    """Predict Gaussians for the batch's pairs and render every target: (rgb [B,T,3,S,S], alpha, Prediction).
    The convolutions run under bf16 autocast on CUDA when ``amp``; the composer and rasteriser in float32."""
    left = batch["left"]
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp and left.is_cuda):
        pred = model(left, batch["right"], batch["K"], batch["baseline"])
    S = batch["targets"].shape[-1]
    rgb, alpha = render_views(pred.gaussians, batch["target_viewmats"], batch["target_Ks"], S, S)
    return rgb, alpha, pred


def create_optimizer(params, device: torch.device, **settings) -> torch.optim.AdamW:
    """AdamW over ``params`` (``settings``: lr, betas, weight_decay); on CUDA its fused kernel (one launch
    for every parameter: 0.4 ms against 6.5 ms a step on an H100, the same update)."""
    return torch.optim.AdamW(params, fused=device.type == "cuda", **settings)


def train_step(model, batch: dict, objective, optimizer: torch.optim.Optimizer, scheduler, amp: bool) -> dict:
    """One optimiser step on one batch; returns loss, its parts, PSNR (dB) and the learning rate used."""
    optimizer.zero_grad(set_to_none=True)
    rgb, _, _ = render_targets(model, batch, amp)
    loss, parts = objective(rgb.flatten(0, 1), batch["targets"].flatten(0, 1))
    if not torch.isfinite(loss):
        raise FloatingPointError(f"non-finite loss ({loss.item()}); resume from checkpoints/last.pt with a lower --lr")
    loss.backward()
    lr = optimizer.param_groups[0]["lr"]
    optimizer.step()
    scheduler.step()
    psnr = metrics.psnr(rgb.detach(), batch["targets"]).mean()
    return {"loss": loss.item(), "psnr": psnr.item(), "lr": lr, **{k: float(v) for k, v in parts.items()}}


@torch.no_grad()
def validate(model, loader, world: World, amp: bool, sheet_samples: int, limit: int | None = None
             ) -> tuple[dict, list]:
    """Mean PSNR over every target of the split (full image and valid pixels only), summed over ranks;
    and the first ``sheet_samples`` samples of this rank for the contact sheet. ``limit`` caps the
    samples each rank validates on (None: all)."""
    was_training = model.training
    model.eval()
    total, total_masked, count, shown = 0.0, 0.0, 0, []
    samples = 0
    for batch in loader:
        if limit is not None and samples >= limit:
            break
        samples += len(batch["keys"])
        batch = to_device(batch, world.device)
        rgb, _, pred = render_targets(model, batch, amp)
        total += metrics.psnr(rgb, batch["targets"]).sum().item()
        total_masked += metrics.psnr(rgb, batch["targets"], batch["masks"]).sum().item()
        count += rgb.shape[0] * rgb.shape[1]
        for i in range(rgb.shape[0]):
            if len(shown) < sheet_samples:
                shown.append({"left": batch["left"][i], "depth": pred.depth[i], "targets": batch["targets"][i],
                              "renders": rgb[i], "key": batch["keys"][i]})
    model.train(was_training)
    total, total_masked, count = all_sum(world, [total, total_masked, float(count)])
    if count == 0:
        raise ValueError("the validation split has no targets")
    return {"val_psnr": total / count, "val_psnr_masked": total_masked / count, "val_targets": int(count)}, shown


def mean_over_ranks(world: World, stats: dict) -> dict:
    """The step's loss, its parts and PSNR averaged over ranks (each rank measured its share of the global
    batch, all shares the same size), so a record means the same on any number of GPUs; lr as it is."""
    keys = [k for k in stats if k != "lr"]
    return {**stats, **dict(zip(keys, (v / world.size for v in all_sum(world, [stats[k] for k in keys]))))}


def to_device(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device, non_blocking=True) if torch.is_tensor(v) else v for k, v in batch.items()}


def _append_jsonl(path: Path, record: dict) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")
        f.flush()


def _trim_metrics(path: Path, step: int) -> None:
    """On resume, drop records written after the checkpoint's step (they will be written again)."""
    if not path.exists():
        return
    keep = [line for line in path.read_text().splitlines() if line.strip() and json.loads(line)["step"] <= step]
    atomic_write_bytes(path, "".join(line + "\n" for line in keep).encode())


def run_config(model_params: ModelParams, train_params: TrainParams, data: Path, encoder, objective) -> dict:
    """The record written to RUN/config.json; a resumed run must match it (except the worker count)."""
    return {"model": model_params.to_dict(), "train": train_params.to_dict(), "data": str(Path(data).resolve()),
            "encoder": {"name": encoder.name, "weights_sha256": encoder.weights_sha256},
            "loss": objective.to_config()}


def _check_resumable(paths: RunPaths, config: dict) -> bool:
    """True to resume; ValueError when RUN holds another run or something that is not a run."""
    if not paths.root.exists() or not any(paths.root.iterdir()):
        return False
    if not paths.config.exists():
        raise ValueError(f"{paths.root}: exists and is not a training run (no config.json); choose another --out")
    old, config = json.loads(paths.config.read_text()), json.loads(json.dumps(config))  # as JSON sees it
    for part in ("model", "data", "encoder", "loss"):
        if old.get(part) != config[part]:
            raise ValueError(f"{paths.root}: was trained with other settings ({part} differs); use a new --out "
                             f"or the same flags")
    old_train = {k: v for k, v in old["train"].items() if k != "workers"}  # workers do not change results
    new_train = {k: v for k, v in config["train"].items() if k != "workers"}
    if old_train != new_train:
        raise ValueError(f"{paths.root}: was trained with other settings (train differs); use a new --out")
    return paths.last.exists()


def train(model_params: ModelParams, train_params: TrainParams, data: Path, out: Path, device: str = "cpu",
          vgg_path: str | None = None, progress: bool = True) -> dict:
    """Train (or resume) a run in ``out``; returns the summary (steps, best validation PSNR, wall time)."""
    model_params.validate()
    train_params.validate()
    world = init_world(device)
    try:
        return _train(model_params, train_params, Path(data), RunPaths(Path(out)), world, vgg_path, progress)
    finally:
        close_world(world)


def _train(model_params: ModelParams, tp: TrainParams, data: Path, paths: RunPaths, world: World,
           vgg_path: str | None, progress: bool) -> dict:
    if tp.batch_size % world.size:
        raise ValueError(f"--batch-size {tp.batch_size} must be divisible by the {world.size} ranks")
    local_batch = tp.batch_size // world.size
    S = model_params.resolution
    read_split_checked(data)
    torch.manual_seed(tp.seed)
    # every training step has the same shapes: let cuDNN time its algorithms once (8% of a step on an H100)
    torch.backends.cudnn.benchmark = world.device.type == "cuda"
    model = create_model(model_params, world.device)
    objective = create_objective(vgg_path, device=world.device, weight=tp.lpips_weight, amp=tp.amp)
    config = run_config(model_params, tp, data, model.encoder, objective)
    resume = _check_resumable(paths, config)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = create_optimizer(params, world.device, lr=tp.lr, betas=tp.betas, weight_decay=tp.weight_decay)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=tp.lr, total_steps=tp.steps,
                                                    pct_start=tp.warmup, div_factor=tp.div_factor,
                                                    final_div_factor=tp.final_div_factor)
    step, best, best_step = 0, float("-inf"), None
    if resume:
        ckpt = load_checkpoint(paths.last, map_location=world.device)
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        step, best, best_step = ckpt["step"], ckpt["best_val_psnr"], ckpt["best_step"]
        torch.set_rng_state(ckpt["rng"]["torch"].cpu())
        if world.device.type == "cuda" and ckpt["rng"].get("cuda") is not None:
            torch.cuda.set_rng_state(ckpt["rng"]["cuda"].cpu(), world.device)
    train_loader = make_loader(data, "train", local_batch, S, tp.targets, tp.seed, tp.workers, world.rank,
                               world.size, train=True, start_step=step)
    val_loader = make_loader(data, "val", local_batch, S, None, tp.seed, tp.workers, world.rank, world.size,
                             train=False)
    if world.main:
        print(f"sgmodel train: {'resuming at step ' + str(step) if resume else 'new run'} in {paths.root}; "
              f"loss {objective.description}; encoder {model.encoder.name}; {world.size} rank(s) on "
              f"{world.device}; batch {tp.batch_size} ({local_batch} per rank) at {S}x{S}", flush=True)
        paths.root.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(paths.config, (json.dumps(config, indent=2) + "\n").encode())
        _trim_metrics(paths.metrics, step)
    net = DistributedDataParallel(model, device_ids=[world.device] if world.device.type == "cuda" else None) \
        if world.size > 1 else model
    net.train()
    t_start = time.perf_counter()
    bar = tqdm(total=tp.steps, initial=step, disable=not (progress and world.main), unit="step", dynamic_ncols=True)

    def validation(step: int, best: float) -> tuple[bool, float]:
        """Validate, log, draw the sheet; (is it the best so far, its PSNR). Step 0 is never the best."""
        val, shown = validate(net, val_loader, world, tp.amp, tp.sheet_samples, tp.val_samples)
        improved = broadcast_flag(world, step > 0 and val["val_psnr"] > best)
        if world.main:
            bar.write(f"step {step}: val PSNR {val['val_psnr']:.2f} dB (valid pixels {val['val_psnr_masked']:.2f})"
                      f"{' best' if improved else ''}")
            _append_jsonl(paths.metrics, {"step": step, **val})
            atomic_write_bytes(paths.sheet(step), validation_sheet(shown))
        return improved, val["val_psnr"]

    if step == 0:  # where training starts from, for the PSNR curve
        validation(0, best)
    batches = iter(train_loader)
    while step < tp.steps:
        t0 = time.perf_counter()
        batch = to_device(next(batches), world.device)
        stats = train_step(net, batch, objective, optimizer, scheduler, tp.amp)
        step += 1
        ms = (time.perf_counter() - t0) * 1e3
        bar.update(1)
        bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}", ms=f"{ms:.0f}")
        if step % tp.log_every == 0 or step == tp.steps:
            stats = mean_over_ranks(world, stats)
            if world.main:
                _append_jsonl(paths.metrics, {"step": step, **stats, "step_ms": ms})
        if step % tp.val_every == 0 or step == tp.steps:
            improved, psnr = validation(step, best)
            if improved:
                best, best_step = psnr, step
            if world.main:
                state = _state(model, config, optimizer, scheduler, step, best, best_step, world)
                save_checkpoint(paths.last, state)
                if improved:
                    save_checkpoint(paths.best, state)
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
    rows = [json.loads(line) for line in metrics_path.read_text().splitlines() if "val_psnr" in line]
    table = format_table([["step", "val PSNR (dB)", "valid-pixel PSNR (dB)", "targets"]] +
                         [[r["step"], f"{r['val_psnr']:.2f}", f"{r['val_psnr_masked']:.2f}", r["val_targets"]]
                          for r in rows], rule=True)
    return (f"{table}\nbest validation PSNR {summary['best_val_psnr']:.2f} dB at step {summary['best_step']}; "
            f"{summary['steps']} steps in {summary['wall_s']:.0f} s; checkpoints in {summary['run']}/checkpoints")


def read_split_checked(data: Path) -> None:
    """Both splits a run needs exist and are readable (DataError naming the file otherwise)."""
    for split in ("train", "val"):
        read_split(Path(data), split)
