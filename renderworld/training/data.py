"""Resumable, rank-sharded data loading.

``ShardedSampler`` is a DistributedSampler that can start mid-epoch, so a resumed run sees
exactly the samples the interrupted run had not yet seen. ``SeededDataset`` makes random
augmentation in DataLoader workers a function of (seed, epoch, sample index) alone, so results
do not depend on the number of workers and a resume mid-epoch is exact; with
``num_workers=0`` samples draw from the main process RNG, which checkpoints hold.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler, get_worker_info

from renderworld.training.seed import sample_seed, worker_init_fn

__all__ = ["ShardedSampler", "SeededDataset", "make_loader"]


class ShardedSampler(Sampler[int]):
    """Indices of one rank's shard of an epoch, optionally shuffled, resumable.

    The permutation depends only on ``(seed, epoch)``, not on the number of ranks, and rank r
    takes positions ``r, r + R, r + 2R, ...`` of it. So the first global batch of R ranks with
    batch size b holds the same samples as the first batch of one process with batch ``R * b``.

    Args:
        num_samples: Dataset length.
        num_replicas: Number of ranks R.
        rank: This rank, in ``[0, R)``.
        shuffle: Permute each epoch.
        seed: Permutation seed.
        drop_last: Drop the tail so every rank gets the same count (training); without it the
            shards may differ by one and no sample is repeated (validation).
    """

    def __init__(
        self,
        num_samples: int,
        *,
        num_replicas: int = 1,
        rank: int = 0,
        shuffle: bool = True,
        seed: int = 0,
        drop_last: bool = True,
    ) -> None:
        if num_samples < 0:
            raise ValueError(f"num_samples: expected >= 0, got {num_samples}")
        if num_replicas < 1 or not 0 <= rank < num_replicas:
            raise ValueError(f"rank: expected 0 <= rank < {num_replicas}, got {rank}")
        self.num_samples = num_samples
        self.num_replicas = num_replicas
        self.rank = rank
        self.shuffle = shuffle
        self.seed = seed
        self.drop_last = drop_last
        self.epoch = 0
        self.start = 0

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        """Select the epoch and skip its first ``start`` samples (a global position, all ranks).

        Positions ``[0, start)`` of the epoch's order are what all ranks consumed together; the
        rest is dealt out again over the current ranks, so a resume may change their number.
        """
        if start < 0:
            raise ValueError(f"start: expected >= 0, got {start}")
        self.epoch = epoch
        self.start = start

    def shard(self) -> list[int]:
        """This rank's indices for the rest of the current epoch (from ``start`` on)."""
        n = self.num_samples
        if self.shuffle:
            gen = torch.Generator().manual_seed(self.seed + self.epoch)
            order = torch.randperm(n, generator=gen).tolist()
        else:
            order = list(range(n))
        order = order[self.start :]
        if self.drop_last:
            order = order[: (len(order) // self.num_replicas) * self.num_replicas]
        return order[self.rank :: self.num_replicas]

    def __iter__(self) -> Iterator[int]:
        return iter(self.shard())

    def __len__(self) -> int:
        return len(self.shard())


class SeededDataset(Dataset):
    """Wrap a map-style dataset so that, in workers, each sample seeds its own RNGs.

    Args:
        dataset: The dataset to wrap.
        seed: Run seed.
    """

    def __init__(self, dataset: Dataset, seed: int) -> None:
        self.dataset = dataset
        self.seed = seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Any:
        if get_worker_info() is not None:
            s = sample_seed(self.seed, self.epoch, int(index))
            random.seed(s)
            np.random.seed(s & 0xFFFFFFFF)  # noqa: NPY002 - user code draws from the global one
            torch.manual_seed(s)
        return self.dataset[index]


def make_loader(
    dataset: Dataset,
    sampler: ShardedSampler,
    *,
    batch_size: int,
    num_workers: int,
    collate_fn: Callable[[list[Any]], Any] | None,
    drop_last: bool,
    pin_memory: bool = False,
    seed: int = 0,
) -> DataLoader:
    """A DataLoader that never touches the global torch RNG.

    An explicit generator seeds the workers' base seed; without it, creating an iterator draws
    from the global RNG, so a resumed run (which creates its iterator at another point of the
    stream) would diverge from the uninterrupted one.
    """
    gen = torch.Generator().manual_seed(seed * 1_000_003 + sampler.epoch * 7919 + sampler.rank)
    return DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=sampler,
        num_workers=num_workers,
        collate_fn=collate_fn,
        drop_last=drop_last,
        pin_memory=pin_memory,
        worker_init_fn=worker_init_fn if num_workers > 0 else None,
        generator=gen,
    )
