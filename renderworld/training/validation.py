"""Validation shared by training and evaluation, and the precision policy.

Validation runs over a rank-sharded, unpadded loader; the stage's additive statistics are
summed over ranks before metrics are computed, and global RNG states are left untouched.
"""

from __future__ import annotations

import warnings
from contextlib import nullcontext
from typing import Any

import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

from renderworld.training.config import TrainerConfig
from renderworld.training.data import ShardedSampler, make_loader
from renderworld.training.distributed import DistInfo, all_reduce_sum
from renderworld.training.registry import Stage
from renderworld.training.seed import rng_isolated

__all__ = [
    "ProgressLoader",
    "autocast_context",
    "effective_precision",
    "build_val_loader",
    "run_validation",
]


#: Device types with an autocast implementation used here.
_AUTOCAST_DEVICES = ("cuda", "cpu")


def autocast_context(precision: str, device: torch.device) -> Any:
    """Autocast for ``"bf16"``/``"fp16"`` on CUDA or CPU; a no-op for ``"32"``.

    Which parts then run in the low precision is the model's business
    (:mod:`renderworld.precision`): networks do, geometry, rendering and losses stay float32.
    """
    if precision == "32" or device.type not in _AUTOCAST_DEVICES:
        return nullcontext()
    dtype = torch.bfloat16 if precision == "bf16" else torch.float16
    return torch.autocast(device_type=device.type, dtype=dtype)


def effective_precision(precision: str, device: torch.device) -> str:
    """``precision`` where autocast exists (CUDA, CPU); 32-bit elsewhere, with a warning.

    On CPU mixed precision runs too (it checks the numerics of a GPU configuration on any
    machine), though it is rarely faster there than 32-bit.
    """
    if precision != "32" and device.type not in _AUTOCAST_DEVICES:
        warnings.warn(
            f"trainer.precision={precision!r} needs CUDA or CPU autocast; training on {device} "
            "in 32-bit",
            RuntimeWarning,
            stacklevel=2,
        )
        return "32"
    return precision


def build_val_loader(
    stage: Stage, dataset: Dataset, tcfg: TrainerConfig, info: DistInfo, seed: int
) -> DataLoader:
    """Validation loader: in order, sharded over ranks without padding or repeats."""
    sampler = ShardedSampler(
        len(dataset),  # type: ignore[arg-type]
        num_replicas=info.world_size,
        rank=info.rank,
        shuffle=False,
        drop_last=False,
    )
    return make_loader(
        dataset,
        sampler,
        batch_size=tcfg.val_batch_size or tcfg.batch_size,
        num_workers=tcfg.num_workers,
        collate_fn=stage.collate_fn(),
        drop_last=False,
        pin_memory=tcfg.pin_memory and info.device.type == "cuda",
        seed=seed,
    )


class ProgressLoader:
    """A loader whose iteration shows a tqdm bar (batches); every other attribute (``dataset``,
    ``batch_size``, ...) is the wrapped loader's, so a stage cannot tell the two apart.

    Args:
        loader: any iterable of batches (its ``len`` gives the bar's total when it has one).
        desc: the bar's label.
    """

    def __init__(self, loader: Any, desc: str = "validation"):
        self.loader = loader
        self.desc = desc

    def __iter__(self):
        from tqdm.auto import tqdm

        total = len(self.loader) if hasattr(self.loader, "__len__") else None
        with tqdm(total=total, desc=self.desc, unit="batch", leave=False,
                  dynamic_ncols=True) as bar:  # fmt: skip
            for batch in self.loader:
                yield batch
                bar.update(1)

    def __len__(self) -> int:
        return len(self.loader)

    def __getattr__(self, name: str) -> Any:
        if name == "loader":  # not set yet (copy, unpickling): no endless recursion
            raise AttributeError(name)
        return getattr(self.loader, name)


def run_validation(
    stage: Stage,
    model: nn.Module,
    loader: DataLoader,
    info: DistInfo,
    precision: str,
    progress: bool = False,
) -> dict[str, float]:
    """Stage statistics on this rank's shard, summed over ranks, turned into ``val/`` metrics.

    Global RNG states are left untouched, so validating does not change training. With
    ``progress`` the main rank shows a bar over the batches (:class:`ProgressLoader`).
    """
    was_training = model.training
    model.eval()
    if progress and info.is_main:
        loader = ProgressLoader(loader, f"{stage.name}: validation")
    try:
        with rng_isolated(), torch.no_grad(), autocast_context(precision, info.device):
            stats = stage.evaluate(model, loader)
    finally:
        model.train(was_training)
    if not isinstance(stats, dict):
        raise TypeError(
            f"{type(stage).__name__}.evaluate: expected a dict of tensors, got {type(stats)}"
        )
    metrics = stage.compute_metrics(all_reduce_sum(stats, info))
    return {f"val/{k}": float(v) for k, v in metrics.items()}
