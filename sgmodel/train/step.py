"""One training step (``queue_step``, ``train_step``): a loader's batch on the device (``device_batch``), the
targets rendered (``render_targets``), the loss, its backward and the optimiser's update, and the step's values on
their way back to the host (``StepValues``), with the checks that keep a step finite. The loop around it, its
validation and what a run writes: ``sgmodel.train.loop``."""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path

import torch
from torch.nn.parallel import DistributedDataParallel

from sgmodel.data.loader import batch_share, map_tensors, to_device
from sgmodel.metrics import image as metrics
from sgmodel.model.layers import amp_autocast
from sgmodel.model.network import StereoGaussians, check_inputs
from sgmodel.model.render import render_views


class TrainingDiverged(ValueError):
    """The loss, a gradient or a weight became NaN or infinite; training stopped and saved nothing of it.
    ``step``: the step it happened at; ``checkpoint``: the last checkpoint written (holding
    ``checkpoint_step``), or None; ``lr``: the peak learning rate used."""

    def __init__(self, message: str, step: int | None = None, checkpoint: Path | None = None,
                 checkpoint_step: int | None = None, lr: float | None = None) -> None:
        super().__init__(message)
        self.step, self.checkpoint, self.checkpoint_step, self.lr = step, checkpoint, checkpoint_step, lr


def render_targets(model: StereoGaussians | DistributedDataParallel, batch: dict, amp: bool):
    """Predict Gaussians for the batch's pairs and render every target: (rgb [B,T,3,S,S], alpha, Prediction).
    The convolutions run under bf16 autocast on CUDA when ``amp``; the composer and rasteriser in float32."""
    left = batch["left"]
    with amp_autocast(left, amp):
        pred = model(left, batch["right"], batch["K"], batch["baseline"], encoded=cached_encoding(batch),
                     inputs_checked=batch.get("inputs_checked", False))
    S = batch["targets"].shape[-1]
    rgb, alpha = render_views(pred.gaussians, batch["target_viewmats"], batch["target_Ks"], S, S)
    return rgb, alpha, pred


#: per CUDA device, the side stream ``device_batch`` copies batches on
_copy_streams: dict[torch.device, torch.cuda.Stream] = {}


def device_batch(batch: dict, device: torch.device) -> dict:
    """A loader's batch on ``device`` for ``render_targets``. Its pair inputs are checked on the host first
    (``network.check_inputs``: K's and the baseline's values read where they are, with no wait for the device)
    and the batch says so (``inputs_checked``): the model does not read them back from the device. On CUDA the
    copy runs on a side stream that the current stream waits for: the copy engine moves the next batch while
    the step before still computes (4.1 ms of the step's stream time on an H200 otherwise)."""
    check_inputs(batch["left"], batch["right"], batch["K"], batch["baseline"])
    if device.type != "cuda":
        return {**to_device(batch, device), "inputs_checked": True}
    device = torch.device("cuda", torch.cuda.current_device() if device.index is None else device.index)
    if device not in _copy_streams:
        _copy_streams[device] = torch.cuda.Stream(device)
    stream, consumer = _copy_streams[device], torch.cuda.current_stream(device)

    def copy(t: torch.Tensor) -> torch.Tensor:
        with torch.cuda.stream(stream):
            moved = t.to(device, non_blocking=True)
        moved.record_stream(consumer)  # made on the side stream, used and freed on the consumer's
        return moved

    moved = map_tensors(batch, copy)
    consumer.wait_stream(stream)
    return {**moved, "inputs_checked": True}


def create_optimizer(params, device: torch.device, **settings) -> torch.optim.AdamW:
    """AdamW over ``params`` (``settings``: lr, betas, weight_decay); on CUDA its fused kernel (one launch
    for every parameter: 0.4 ms against 6.5 ms a step on an H100, the same update)."""
    return torch.optim.AdamW(params, fused=device.type == "cuda", **settings)


def no_mark(_: str) -> None:
    """``queue_step``'s ``mark`` when nothing is profiled."""


class StepValues:
    """A queued step's loss, its parts and PSNR on their way to the host, and the learning rate it used
    (``queue_step``). On CUDA they are copied into page-locked memory behind the step's work and ``read`` waits
    for that copy alone: read once the next step is queued, as ``sgmodel train`` does, the host never waits for
    the GPU between steps and the GPU never waits for the host."""

    def __init__(self, values: torch.Tensor, names: list[str], lr: float) -> None:
        self.names, self.lr, self.ready = names, lr, None
        if values.is_cuda:
            self.host = torch.empty(values.shape, dtype=values.dtype, pin_memory=True)
            self.host.copy_(values, non_blocking=True)
            self.ready = torch.cuda.Event()
            self.ready.record()
        else:
            self.host = values

    def read(self) -> dict:
        """{"loss", "psnr", "lr", and the loss's parts} as numbers; ``TrainingDiverged`` for a non-finite loss (the
        step changed no weight: ``skip_unless_finite``)."""
        if self.ready is not None:
            self.ready.synchronize()
        values = self.host.tolist()
        if not math.isfinite(values[0]):
            raise TrainingDiverged(f"the loss is {values[0]}")
        return {"loss": values[0], "psnr": values[1], "lr": self.lr, **dict(zip(self.names, values[2:]))}


def train_step(model, batch: dict, objective, optimizer: torch.optim.Optimizer, scheduler, amp: bool,
               mark=no_mark, accumulate: int = 1) -> dict:
    """``queue_step`` and its values read at once: loss, its parts, PSNR (dB) and the learning rate used."""
    return queue_step(model, batch, objective, optimizer, scheduler, amp, mark, accumulate).read()


def queue_step(model, batch: dict, objective, optimizer: torch.optim.Optimizer, scheduler, amp: bool,
               mark=no_mark, accumulate: int = 1) -> StepValues:
    """Queue one optimiser step on one batch; its values come back through the returned ``StepValues``.
    ``accumulate``: the batch is computed in that many equal shares (``batch_share``), one after another,
    each share's loss divided by their number: the gradient is the mean of the shares' gradients, as DDP's
    is the mean of its ranks' (under DDP the all-reduce runs once, after the last share). The values are the
    shares' means. ``mark(name)``: called once the loss ("forward"), the backward ("backward") and the
    optimiser step ("optimizer") are queued (``StepProfile.mark``; with shares, the last share's loss and
    backward). A batch from ``device_batch`` makes no host synchronisation on a GPU."""
    optimizer.zero_grad(set_to_none=True)
    values = []
    for i in range(accumulate):
        part, last = batch_share(batch, i, accumulate), i == accumulate - 1
        with model.no_sync() if not last and isinstance(model, DistributedDataParallel) else nullcontext():
            rgb, _, _ = render_targets(model, part, amp)
            loss, parts = objective(rgb.flatten(0, 1), part["targets"].flatten(0, 1))
            if last:
                mark("forward")
            (loss / accumulate).backward()
        psnr = metrics.psnr(rgb.detach(), part["targets"]).mean()
        values.append(torch.stack([loss.detach(), psnr, *(v.detach() for v in parts.values())]))
    mark("backward")
    values = torch.stack(values).mean(0)
    skip_unless_finite(optimizer, values[0])
    lr = optimizer.param_groups[0]["lr"]
    optimizer.step()
    scheduler.step()
    mark("optimizer")
    return StepValues(values, list(parts), lr)


def steps_back_to_back(queue: Callable[[int], StepValues], steps: int) -> None:
    """Queue steps 0 .. ``steps`` - 1 (``queue(i)``), each one's values read once the next is queued, as
    ``sgmodel train`` runs them (its loop also logs); the last step's read at the end. For the benchmarks."""
    queued = None
    for i in range(steps):
        values = queue(i)
        if queued is not None:
            queued.read()
        queued = values
    if queued is not None:
        queued.read()


def skip_unless_finite(optimizer: torch.optim.Optimizer, loss: torch.Tensor) -> None:
    """Make sure a non-finite ``loss`` changes no weight in the ``optimizer.step()`` that follows. A fused
    optimizer (``create_optimizer`` on CUDA) is given ``found_inf`` (as ``torch.amp.GradScaler`` gives it): its
    kernel leaves the weights, moments and step count as they were where the flag is set, decided on the device,
    so the host queues the step right after the backward instead of waiting for the loss (the GPU stood idle
    about 1 ms a step while the host then started the optimiser). Any other optimiser: the loss is read here
    (``TrainingDiverged``), which on the CPU costs nothing."""
    if optimizer.defaults.get("fused"):
        optimizer.found_inf = (~torch.isfinite(loss)).float()
    elif not torch.isfinite(loss):
        raise TrainingDiverged(f"the loss is {loss.item()}")


def cached_encoding(batch: dict) -> tuple[torch.Tensor, list[torch.Tensor]] | None:
    """The batch's frozen-encoder outputs read from an encoder cache (disparity, features), or None."""
    return (batch["encoder_disparity"], batch["encoder_features"]) if "encoder_disparity" in batch else None


def all_finite(tensors: list[torch.Tensor]) -> torch.Tensor:
    """True (a 0-d bool tensor on their device, no sync) when every value of every tensor is finite: one
    fused multi-tensor norm (``torch._foreach_norm``), which is NaN or infinite exactly when a value is (or
    when a float32 norm overflows, above 1e19: a divergence too)."""
    if not tensors:
        return torch.tensor(True)
    return torch.stack(torch._foreach_norm(tensors)).isfinite().all()
