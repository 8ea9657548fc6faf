"""Several GPUs through ``torchrun``: one process per GPU, NCCL (gloo on CPU), only rank 0 writes.

``torchrun --nproc_per_node=N -m sgmodel.cli train ...`` sets RANK, LOCAL_RANK and WORLD_SIZE; a plain
``sgmodel train`` is a world of one. No home-made launcher.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch.distributed.algorithms.ddp_comm_hooks.default_hooks import bf16_compress_hook
from torch.nn.parallel import DistributedDataParallel

#: DDP's gradient bucket size (MiB) unless ``--ddp-bucket-mb`` says otherwise (PyTorch's default)
BUCKET_MB = 25


@dataclass(frozen=True)
class World:
    rank: int  # this process, 0..size-1
    size: int  # processes in the job
    device: torch.device  # this process's device
    local_size: int = 1  # processes of the job on this host (torchrun's LOCAL_WORLD_SIZE)

    @property
    def main(self) -> bool:
        """Rank 0: the only process that writes files and shows progress."""
        return self.rank == 0


def init_world(device: str) -> World:
    """Join the ``torchrun`` job if there is one; pick this rank's device (cuda:LOCAL_RANK on GPUs)."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return World(0, 1, torch.device(device))
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if device.startswith("cuda"):
        torch.cuda.set_device(local)
        dev = torch.device("cuda", local)
        dist.init_process_group("nccl", device_id=dev)
    else:
        dev = torch.device(device)
        dist.init_process_group("gloo")
    return World(rank, size, dev, int(os.environ.get("LOCAL_WORLD_SIZE", size)))


@contextmanager
def joined_world(device: str) -> Iterator[World]:
    """``init_world`` for the block, then ``close_world``: finished (every rank waited for) when the block ends
    without an error, at once after one."""
    world, finished = init_world(device), False
    try:
        yield world
        finished = True
    finally:
        close_world(world, finished)


def close_world(world: World, finished: bool = False) -> None:
    """Leave the job (nothing in a world of one). ``finished``: this rank's work ended without an error, so every
    rank is waited for first (rank 0 may still be writing its last checkpoint), and no rank tears down its
    connections while another is still in the job: the likely cause, not reproduced, of a gloo rank that once
    ended in SIGABRT ("terminate called without an active exception") at the end of a CI run. After an error
    there is no wait: the others may never come, and torchrun ends them."""
    if world.size > 1 and dist.is_initialized():
        if finished:
            dist.barrier()
        dist.destroy_process_group()


def all_sum(world: World, values: list[float]) -> list[float]:
    """Element-wise sum of ``values`` over ranks (float64 on the rank's device)."""
    if world.size == 1:
        return values
    t = torch.tensor(values, dtype=torch.float64, device=world.device)
    dist.all_reduce(t)
    return t.tolist()


def all_gather_rows(world: World, values: list[float]) -> list[list[float]]:
    """Every rank's ``values`` (the same length on every rank), in rank order (float64 on the rank's device)."""
    if world.size == 1:
        return [list(values)]
    t = torch.tensor(values, dtype=torch.float64, device=world.device)
    rows = [torch.empty_like(t) for _ in range(world.size)]
    dist.all_gather(rows, t)
    return [r.tolist() for r in rows]


def wrap_model(model: torch.nn.Module, world: World, bucket_mb: float = BUCKET_MB, bf16_grads: bool = False
               ) -> torch.nn.Module:
    """``model`` under DDP on several ranks (itself on one). Its gradients are views into DDP's buckets (no
    copy between them and ``.grad``). Not ``static_graph``: with it the first step's gradients of the
    predictor's back-layer head come out wrong (tests/sgmodel/train/test_distributed.py holds DDP's gradient against one
    process's). ``bf16_grads``: each bucket is all-reduced in bfloat16 (half the bytes, the mean rounded to
    bf16 before the optimiser sees it: a different run)."""
    if world.size == 1:
        return model
    net = DistributedDataParallel(model, device_ids=[world.device] if world.device.type == "cuda" else None,
                                  bucket_cap_mb=bucket_mb, gradient_as_bucket_view=True)
    if bf16_grads:
        net.register_comm_hook(dist.group.WORLD, bf16_compress_hook)
    return net


def same_on_every_rank(world: World, value: int) -> bool:
    """Whether every rank holds the same ``value`` (an integer below 2**53)."""
    if world.size == 1:
        return True
    return len({row[0] for row in all_gather_rows(world, [float(value)])}) == 1


def barrier(world: World) -> None:
    """Wait until every rank gets here (nothing in a world of one)."""
    if world.size > 1:
        dist.barrier()


def broadcast_flag(world: World, flag: bool) -> bool:
    """Rank 0's ``flag`` on every rank (a decision only rank 0 can make, e.g. a new best checkpoint)."""
    if world.size == 1:
        return flag
    t = torch.tensor([1 if flag else 0], device=world.device)
    dist.broadcast(t, 0)
    return bool(t.item())
