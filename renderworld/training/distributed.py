"""Process-group set-up from ``torchrun``'s environment, and the few collectives the loop uses.

Launched plainly, a run is one process and every collective is the identity. Launched with
``torchrun --nproc_per_node=N``, ``RANK``/``WORLD_SIZE``/``LOCAL_RANK`` are set and the run joins
a process group: NCCL when it trains on CUDA, gloo on CPU.
"""

from __future__ import annotations

import gc
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

__all__ = [
    "DistInfo",
    "init_distributed",
    "shutdown_distributed",
    "resolve_device",
    "all_reduce_sum",
    "broadcast_object",
    "all_gather_object",
    "any_rank",
    "barrier",
]


@dataclass(frozen=True)
class DistInfo:
    """Where this process stands.

    Attributes:
        rank: Global rank (0 for a single process).
        world_size: Number of processes.
        local_rank: Rank on this machine (selects the CUDA device).
        device: The device this process trains on.
        owns_group: True if ``init_distributed`` created the process group (and so must
            destroy it).
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    owns_group: bool = False

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that logs and writes checkpoints."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        """More than one process."""
        return self.world_size > 1


def resolve_device(preference: str, local_rank: int = 0) -> torch.device:
    """Map ``"auto" | "cpu" | "cuda[:i]"`` to a device, using ``local_rank`` under torchrun.

    Raises:
        ValueError: CUDA is asked for and not available, or the string is unknown.
    """
    if preference == "cpu":
        return torch.device("cpu")
    if preference == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda", local_rank)
        return torch.device("cpu")
    if preference.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(
                f"trainer.device: {preference!r} requested but CUDA is not available "
                "(use trainer.device=cpu or auto)"
            )
        return torch.device(preference) if ":" in preference else torch.device("cuda", local_rank)
    raise ValueError(f"trainer.device: expected 'auto', 'cpu' or 'cuda[:i]', got {preference!r}")


def init_distributed(device_preference: str = "auto") -> DistInfo:
    """Join the process group described by torchrun's environment, if any.

    Returns:
        DistInfo for this process. A plain launch gives rank 0 of 1 without a group.
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    device = resolve_device(device_preference, local_rank)
    if world_size <= 1:
        return DistInfo(device=device)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    owns = False
    if not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        kwargs: dict[str, Any] = {"backend": backend}
        if backend == "nccl":
            kwargs["device_id"] = device
        dist.init_process_group(**kwargs)
        owns = True
    return DistInfo(rank, world_size, local_rank, device, owns)


def shutdown_distributed(info: DistInfo) -> None:
    """Destroy the process group if ``init_distributed`` created it.

    All ranks meet at a barrier first: a rank that tears gloo down while a peer is still
    receiving aborts the peer ("terminate called without an active exception", seen in CI).
    Unreachable objects are collected before that: a DDP reducer still alive in a reference
    cycle holds gloo works whose late release aborts the process in the same way.
    """
    if info.owns_group and dist.is_initialized():
        gc.collect()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                dist.barrier()
            except RuntimeError:  # a peer already died; tearing down is all that is left
                pass
            dist.destroy_process_group()


def all_reduce_sum(stats: Mapping[str, torch.Tensor], info: DistInfo) -> dict[str, torch.Tensor]:
    """Sum tensors over ranks (identity for one process); results come back on CPU, float64.

    Every rank must pass the same keys with the same shapes.

    Raises:
        ValueError: ranks disagree on the keys.
    """
    out = {k: torch.as_tensor(v).detach().to(torch.float64).cpu() for k, v in stats.items()}
    if not info.distributed:
        return out
    keys = sorted(out)
    all_keys = all_gather_object(keys, info)
    if any(k != keys for k in all_keys):
        raise ValueError(f"all_reduce_sum: ranks returned different statistics: {all_keys}")
    comm_device = info.device if info.device.type == "cuda" else torch.device("cpu")
    for k in keys:
        t = out[k].to(comm_device)
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
        out[k] = t.cpu()
    return out


def broadcast_object(obj: Any, info: DistInfo, src: int = 0) -> Any:
    """Rank ``src``'s ``obj`` on every rank (picklable objects)."""
    if not info.distributed:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=src)
    return box[0]


def all_gather_object(obj: Any, info: DistInfo) -> list[Any]:
    """Every rank's ``obj``, in rank order."""
    if not info.distributed:
        return [obj]
    out: list[Any] = [None] * info.world_size
    dist.all_gather_object(out, obj)
    return out


def any_rank(flag: bool, info: DistInfo) -> bool:
    """True on every rank if ``flag`` is true on any rank (keeps ranks in lock-step)."""
    if not info.distributed:
        return flag
    dev = info.device if info.device.type == "cuda" else torch.device("cpu")
    t = torch.tensor([1 if flag else 0], device=dev)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


def barrier(info: DistInfo) -> None:
    """Wait for every rank (no-op for one process)."""
    if info.distributed:
        dist.barrier()
