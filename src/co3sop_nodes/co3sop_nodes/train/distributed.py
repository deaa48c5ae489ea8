"""Data-parallel training under torchrun: which process this is, its device, the process group (ROS-free).

`torchrun --nproc-per-node N [--nnodes M ...] train ...` starts N processes per
machine and tells each its place through the environment (RANK, WORLD_SIZE,
LOCAL_RANK, LOCAL_WORLD_SIZE, MASTER_ADDR/PORT); `train` started without it
is a world of one. Gradients are averaged by DistributedDataParallel over
gloo on CPUs and NCCL on GPUs (one GPU per process, cuda:LOCAL_RANK).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.model.path import resolve_device


@dataclass(frozen=True)
class World:
    rank: int = 0  # this process among all
    size: int = 1  # processes in all
    local_rank: int = 0  # this process on its machine
    local_size: int = 1  # processes on this machine

    @property
    def main(self) -> bool:
        """The one process that writes logs, checkpoints and the exported model."""
        return self.rank == 0


def world_from_env(env=os.environ) -> World:
    """This process's place, as torchrun sets it (a world of one without torchrun)."""
    try:
        size = int(env.get("WORLD_SIZE", "1"))
        return World(
            int(env.get("RANK", "0")),
            size,
            int(env.get("LOCAL_RANK", "0")),
            int(env.get("LOCAL_WORLD_SIZE", str(size))),
        )
    except ValueError as exc:
        raise Co3sopError(f"torchrun's environment is malformed: {exc}") from None


def device_for(world: World, name: str) -> torch.device:
    """`--device` for this process: under torchrun each process takes the GPU of its local rank."""
    device = resolve_device(name, "--device")
    if world.size > 1 and device.type == "cuda":
        if device.index not in (None, world.local_rank):
            raise Co3sopError(f"--device {name}: under torchrun each process uses cuda:LOCAL_RANK; pass --device cuda")
        device = resolve_device(f"cuda:{world.local_rank}", "--device")
    return device


def start(world: World, device: torch.device) -> None:
    """Joins the process group (NCCL for GPUs, gloo for CPUs); nothing for a world of one."""
    if world.size > 1:
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")


def finish(world: World) -> None:
    """Waits at the end of a run until every process is there: rank 0 writes the checkpoint, the exported model
    and the plot after the last step, and a process that left the group meanwhile could end the run under it
    (torchrun stops the others when one exits badly)."""
    if world.size > 1:
        dist.barrier()


def stop(world: World) -> None:
    if world.size > 1 and dist.is_initialized():
        dist.destroy_process_group()


def mean_over_world(world: World, values: dict[str, float], device: torch.device) -> dict[str, float]:
    """Each value averaged over the processes (what the logged losses of a global batch are)."""
    if world.size == 1:
        return values
    t = torch.tensor(list(values.values()), dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return dict(zip(values, (t / world.size).tolist()))
