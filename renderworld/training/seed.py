"""Seeding and RNG state capture (python, numpy, torch CPU and CUDA).

States are captured as tensors, lists and primitives only, so checkpoints holding them load
with ``torch.load(weights_only=True)``.
"""

# The legacy global numpy RNG is what user code draws from; seeding and saving it is the point.
# ruff: noqa: NPY002

from __future__ import annotations

import random
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch

__all__ = [
    "seed_everything",
    "get_rng_state",
    "set_rng_state",
    "rng_isolated",
    "worker_init_fn",
    "sample_seed",
]

_MASK32 = 0xFFFFFFFF


def seed_everything(seed: int) -> None:
    """Seed python ``random``, numpy's global RNG and torch (CPU and every CUDA device).

    Raises:
        TypeError: ``seed`` is not an int.
    """
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise TypeError(f"seed: expected an int, got {type(seed).__name__}")
    random.seed(seed)
    np.random.seed(seed & _MASK32)
    torch.manual_seed(seed)


def get_rng_state() -> dict[str, Any]:
    """Capture every global RNG state as weights-only-loadable values."""
    version, words, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state: dict[str, Any] = {
        "python": {"version": int(version), "state": [int(w) for w in words], "gauss": gauss},
        "numpy": {
            "name": str(name),
            "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached),
        },
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore states captured by ``get_rng_state``.

    Raises:
        ValueError: ``state`` lacks one of the python / numpy / torch entries.
    """
    missing = [k for k in ("python", "numpy", "torch") if k not in state]
    if missing:
        raise ValueError(f"state: RNG state lacks {missing}")
    py = state["python"]
    random.setstate((py["version"], tuple(py["state"]), py["gauss"]))
    npy = state["numpy"]
    keys = npy["keys"].numpy().astype(np.uint32)
    np.random.set_state((npy["name"], keys, npy["pos"], npy["has_gauss"], npy["cached_gaussian"]))
    torch.set_rng_state(state["torch"])
    cuda = state.get("cuda") or []
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)


@contextmanager
def rng_isolated() -> Iterator[None]:
    """Run a block without disturbing any global RNG (used around validation).

    Validation that draws random numbers would otherwise shift the training stream, so a run
    would depend on how often it validated and resume would not be exact.
    """
    state = get_rng_state()
    try:
        yield
    finally:
        set_rng_state(state)


def sample_seed(base_seed: int, epoch: int, index: int) -> int:
    """A 63-bit seed for one sample of one epoch, independent of worker count and rank."""
    # splitmix64-style mixing: nearby (epoch, index) pairs give unrelated seeds.
    x = (base_seed * 0x9E3779B97F4A7C15 + epoch * 0xBF58476D1CE4E5B9 + index) & (2**64 - 1)
    x ^= x >> 30
    x = (x * 0xBF58476D1CE4E5B9) & (2**64 - 1)
    x ^= x >> 27
    x = (x * 0x94D049BB133111EB) & (2**64 - 1)
    x ^= x >> 31
    return x >> 1


def worker_init_fn(worker_id: int) -> None:
    """DataLoader worker init: seed python and numpy from torch's per-worker seed.

    torch already gives each worker ``base_seed + worker_id``; without this, numpy and python
    ``random`` would be identical copies in every worker (the classic duplicated-augmentation
    bug).
    """
    seed = torch.initial_seed()
    random.seed(seed)
    np.random.seed(seed & _MASK32)
