"""Several GPUs through ``torchrun``: one process per GPU, NCCL (gloo on CPU), only rank 0 writes.

``torchrun --nproc_per_node=N -m sgmodel.cli train ...`` sets RANK, LOCAL_RANK and WORLD_SIZE; a plain
``sgmodel train`` is a world of one. No home-made launcher.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class World:
    rank: int  # this process, 0..size-1
    size: int  # processes in the job
    device: torch.device  # this process's device

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
    return World(rank, size, dev)


def close_world(world: World) -> None:
    if world.size > 1 and dist.is_initialized():
        dist.destroy_process_group()


def all_sum(world: World, values: list[float]) -> list[float]:
    """Element-wise sum of ``values`` over ranks (float64 on the rank's device)."""
    if world.size == 1:
        return values
    t = torch.tensor(values, dtype=torch.float64, device=world.device)
    dist.all_reduce(t)
    return t.tolist()


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
