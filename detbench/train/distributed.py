"""Multi-process training with PyTorch's own launcher: `torchrun --nproc_per_node=N tools/train.py ...`.

torchrun sets RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT; `init_distributed`
reads them (no variables -> one process, nothing to initialise), picks the backend (nccl
for CUDA, gloo for CPU) and the device (cuda:LOCAL_RANK). Each process then wraps the model
in DistributedDataParallel and reads its share of the data through a DistributedSampler.
Only rank 0 writes logs and checkpoints; loss figures are averaged over ranks for logging.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from collections.abc import Iterator, Mapping

import torch
import torch.distributed as dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel

__all__ = ["DeviceError", "DistInfo", "init_distributed", "launch_ranks", "resolve_device", "wrap_model", "reduce_mean",
           "any_rank", "sync_buffers", "barrier", "main_process_first", "cleanup"]


@dataclass(frozen=True)
class DistInfo:
    """This process's place in the job."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def is_main(self) -> bool:
        """True on the process that writes logs and checkpoints (rank 0)."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def launch_ranks() -> tuple[int, int, int]:
    """(rank, world size, local rank) torchrun set in the environment; (0, 1, 0) for a single process."""
    def read(name: str, default: int) -> int:
        value = os.environ.get(name, "") or str(default)
        if not value.isdigit():
            raise ValueError(f"environment variable {name}={value!r}: not a rank count; torchrun sets it, unset it "
                             f"to run a single process")
        return int(value)

    return read("RANK", 0), read("WORLD_SIZE", 1), read("LOCAL_RANK", 0)


class DeviceError(ValueError):
    """A device this process cannot train on; `device` is the name asked for, `reason` what is wrong and the fix."""

    def __init__(self, device: str, reason: str):
        super().__init__(f"device {device}: {reason}")
        self.device, self.reason = device, reason


def resolve_device(device: str, local_rank: int = 0, world_size: int = 1) -> torch.device:
    """The torch device `device` names for this process, checked against what torch sees (no side effects).

    `device` is "auto" (CUDA when available), "cpu", "cuda" or "cuda:N". One process: "cuda" is cuda:0 and
    "cuda:N" the N-th visible GPU. Several processes (torchrun): each takes cuda:LOCAL_RANK, so only "cuda" or
    "auto" is accepted (the GPUs are chosen with CUDA_VISIBLE_DEVICES). `DeviceError` otherwise.
    """
    name = str(device).strip()
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise DeviceError(device, "not a device; use auto, cpu, cuda or cuda:N") from None
    if dev.type == "cpu":
        return torch.device("cpu")
    if dev.type != "cuda":
        raise DeviceError(device, "training runs on cpu or cuda; use auto, cpu, cuda or cuda:N")
    if not torch.cuda.is_available():
        raise DeviceError(device, "torch sees no CUDA device (a CPU-only torch build or no GPU); use --device cpu")
    n = torch.cuda.device_count()
    if world_size > 1:
        if dev.index is not None:
            raise DeviceError(device, f"under torchrun each of the {world_size} processes takes cuda:LOCAL_RANK; give "
                                      f"--device cuda and choose the GPUs with CUDA_VISIBLE_DEVICES")
        if local_rank >= n:
            raise DeviceError(device, f"LOCAL_RANK={local_rank} but only {n} CUDA device(s) are visible; use "
                                      f"torchrun --nproc_per_node<={n}")
        return torch.device("cuda", local_rank)
    index = 0 if dev.index is None else dev.index
    if index >= n:
        raise DeviceError(device, f"only {n} CUDA device(s) are visible (cuda:0 to cuda:{n - 1}); "
                                  f"CUDA_VISIBLE_DEVICES chooses which")
    return torch.device("cuda", index)


def init_distributed(device: str = "auto", timeout_minutes: float = 60.0) -> DistInfo:
    """Join the process group torchrun describes in the environment, or run as a single process.

    Args:
        device: "auto" (CUDA when available), "cpu", "cuda" or "cuda:N" (one process; under torchrun each
            process takes cuda:LOCAL_RANK), checked by `resolve_device` (`DeviceError`).
        timeout_minutes: how long collectives wait for a slow rank (rank 0 evaluates and
            writes checkpoints while the others wait).
    Returns:
        DistInfo(rank, world_size, local_rank, device).
    """
    rank, world, local_rank = launch_ranks()
    dev = resolve_device(device, local_rank, world)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if world > 1 and not dist.is_initialized():
        missing = [k for k in ("MASTER_ADDR", "MASTER_PORT") if k not in os.environ]
        if missing:
            raise ValueError(f"WORLD_SIZE={world} but {missing} not set; start multi-process runs with "
                               f"torchrun --nproc_per_node=N tools/train.py ...")
        backend = "nccl" if dev.type == "cuda" else "gloo"
        dist.init_process_group(backend=backend, rank=rank, world_size=world,
                                timeout=timedelta(minutes=timeout_minutes))
    return DistInfo(rank=rank, world_size=world, local_rank=local_rank, device=dev)


def wrap_model(model: nn.Module, info: DistInfo, find_unused_parameters: bool = False) -> nn.Module:
    """DistributedDataParallel around `model` (already on `info.device`) when there are several ranks."""
    if not info.distributed:
        return model
    if info.device.type == "cuda":
        return DistributedDataParallel(model, device_ids=[info.device.index], output_device=info.device.index,
                                       find_unused_parameters=find_unused_parameters)
    return DistributedDataParallel(model, find_unused_parameters=find_unused_parameters)


def reduce_mean(values: Mapping[str, float], info: DistInfo) -> dict[str, float]:
    """Average scalar figures over ranks (every rank must pass the same keys, in any order)."""
    keys = sorted(values)
    if not info.distributed or not keys:
        return {k: float(values[k]) for k in keys}
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=info.device)
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    t /= info.world_size
    return {k: float(v) for k, v in zip(keys, t.tolist())}


def any_rank(flags: list[bool], info: DistInfo) -> list[bool]:
    """Each flag True on every rank when it is True on any rank (e.g. 'stop requested'), in one all-reduce."""
    if not info.distributed:
        return flags
    t = torch.tensor([int(f) for f in flags], dtype=torch.int32, device=info.device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return [bool(x) for x in t.tolist()]


def sync_buffers(model: nn.Module, info: DistInfo) -> None:
    """Average floating-point buffers (BatchNorm running statistics) over ranks; copy rank 0's others.

    DDP copies rank 0's buffers into every rank at each forward, but each rank then updates
    them from its own batch, so after the last step they differ. The loop calls this at each
    epoch end, before the checkpoint, so every rank holds the same (all-data) statistics.
    """
    if not info.distributed:
        return
    with torch.no_grad():
        for buf in model.buffers():
            if buf.is_floating_point():
                dist.all_reduce(buf, op=dist.ReduceOp.SUM)
                buf /= info.world_size
            else:
                dist.broadcast(buf, src=0)


def barrier(info: DistInfo) -> None:
    """Wait for every rank (no-op in a single process)."""
    if info.distributed:
        if info.device.type == "cuda":
            dist.barrier(device_ids=[info.device.index])
        else:
            dist.barrier()


@contextmanager
def main_process_first(info: DistInfo) -> Iterator[None]:
    """Run the block on rank 0 first, then on the others (e.g. build a cache once, then read it)."""
    if not info.is_main:
        barrier(info)
    yield
    if info.is_main:
        barrier(info)


def cleanup(info: DistInfo, wait_for_peers: bool = True) -> None:
    """Leave the process group (call once at the end of a run).

    At the end of a run every rank waits for the others first: a rank that tore its group down
    while a peer was still finishing made the peer's gloo threads abort ("terminate called
    without an active exception", SIGABRT) in about one two-process run in five on CPU. On an
    error path pass `wait_for_peers=False`: the other ranks may never get here, and a barrier
    would hang the failing rank instead of letting it report its error."""
    if info.distributed and dist.is_initialized():
        if wait_for_peers:
            dist.barrier()
        dist.destroy_process_group()
