"""Where a training step's time goes, on every rank (``sgmodel train --profile``).

Each step is cut at marks: ``start`` (the batch is on the device), the frozen encoder's start and end (its
forward hooks; absent when the outputs come from an encoder cache), ``forward`` (the loss is computed),
``grads`` (the last trainable gradient is accumulated: a post-accumulate-grad hook), ``backward``
(``loss.backward()`` returned: under DDP the default stream has then waited for the gradients' all-reduce),
``optimizer`` (AdamW and the schedule stepped). On CUDA the marks are CUDA events on the current stream:
recording one does not wait for the GPU, and they are read after the step's own sync (the ``.tolist()`` of
its statistics), so profiling adds no sync. On the CPU every operation runs in order on the host and the
marks are ``time.perf_counter`` readings.

The phases, milliseconds (``PHASES``): ``data`` (host time waiting for the loader's next batch and queueing
its copy to the device), ``encoder``, ``forward`` (the rest of the forward and the loss), ``backward``
(until the last gradient), ``allreduce`` (the exposed part of DDP's gradient all-reduce: from the last
gradient until the backward returns; on one process the little the autograd engine does after its last
gradient), ``optimizer``; ``cache_mb``: the encoder-cache bytes of this rank's batch (what it read from
the cache for the step). GPU phases are stream time between marks, host stalls included. With ``--accumulate
N`` the encoder and forward marks are the last share's: ``forward`` then holds the N - 1 shares before it,
their backward passes included.
"""

from __future__ import annotations

import time

import torch

from sgmodel.train.distributed import World, all_gather_rows

PHASES = ("data", "encoder", "forward", "backward", "allreduce", "optimizer", "cache_mb")


class _HostMark:
    """A mark on the CPU: the host clock (operations there run in order)."""

    def __init__(self) -> None:
        self.t = time.perf_counter()

    def ms_since(self, other: _HostMark) -> float:
        return (self.t - other.t) * 1e3


class _CudaMark:
    def __init__(self) -> None:
        self.event = torch.cuda.Event(enable_timing=True)
        self.event.record()

    def ms_since(self, other: _CudaMark) -> float:
        return other.event.elapsed_time(self.event)


class StepProfile:
    """Marks of the current step (``mark``; the encoder and gradient marks come from hooks on ``model``'s
    encoder and on ``params``) and the phases of the last finished step (``phases``)."""

    def __init__(self, model, params: list[torch.Tensor], device: torch.device) -> None:
        self._make = _CudaMark if device.type == "cuda" else _HostMark
        self.marks: dict[str, object] = {}
        self._grads_seen, self._grads_expected = 0, None  # the gradients a step accumulates (learnt in step 1)
        encoder = model.encoder
        encoder.register_forward_pre_hook(lambda *_: self.mark("encoder_start"))
        encoder.register_forward_hook(lambda *_: self.mark("encoder_end"))
        for p in params:
            p.register_post_accumulate_grad_hook(self._grad_done)

    def mark(self, name: str) -> None:
        self.marks[name] = self._make()

    def _grad_done(self, _: torch.Tensor) -> None:
        self._grads_seen += 1
        if self._grads_expected is None or self._grads_seen == self._grads_expected:
            self.mark("grads")

    def begin(self) -> None:
        """The batch is on the device: a new step starts."""
        self.marks, self._grads_seen = {}, 0
        self.mark("start")

    def phases(self, data_ms: float, batch: dict) -> dict[str, float]:
        """The finished step's phases (ms; see the module docstring). Call after the step's sync."""
        if self._grads_expected is None:
            self._grads_expected = self._grads_seen
        m = self.marks

        def span(a: str, b: str) -> float:
            return m[b].ms_since(m[a]) if a in m and b in m else 0.0

        encoder = span("encoder_start", "encoder_end")
        grads = "grads" if "grads" in m else "backward"
        cached = [batch["encoder_disparity"], *batch["encoder_features"]] if "encoder_disparity" in batch else []
        return {"data": data_ms, "encoder": encoder, "forward": span("start", "forward") - encoder,
                "backward": span("forward", grads), "allreduce": span(grads, "backward"),
                "optimizer": span("backward", "optimizer"),
                "cache_mb": sum(t.numel() * t.element_size() for t in cached) / 2**20}


def gathered_record(world: World, values: dict[str, float], means: dict[str, float] | None = None) -> dict:
    """``values`` of every rank, gathered: {name: [rank 0's, rank 1's, ...]}, rounded to 0.01 (ms) for
    ``metrics.jsonl``; and, in the same collective, ``means`` averaged over ranks ({name: mean}: a step's
    loss and PSNR, as ``train.mean_over_ranks``)."""
    means = means or {}
    rows = all_gather_rows(world, [*means.values(), *values.values()])
    out = {name: sum(row[i] for row in rows) / world.size for i, name in enumerate(means)}
    out.update({name: [round(row[len(means) + i], 2) for row in rows] for i, name in enumerate(values)})
    return out
