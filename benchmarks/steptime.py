"""Time a training step: one warm-up, then the median of repeated steps, and peak memory.

Shared by the benchmark scripts beside it (run as ``python benchmarks/<script>.py``, which puts
this folder on ``sys.path``).
"""

from __future__ import annotations

import resource
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["StepTiming", "time_steps"]


@dataclass
class StepTiming:
    """``first_s``: the warm-up step, seconds; ``step_s``: median of the timed steps, seconds;
    ``peak_mb``: peak CUDA memory allocated, or growth of the process's peak RSS on CPU (MiB);
    ``warmup``: what the warm-up step returned."""

    first_s: float
    step_s: float
    peak_mb: float
    warmup: Any


def time_steps(step: Callable[[int], Any], repeats: int, device: torch.device) -> StepTiming:
    """Run ``step(0)`` once to warm up, then ``step(i)`` for ``i < repeats``, timing each.

    ``step`` must synchronise its device before returning (CUDA kernels run asynchronously).
    """
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    warmup = step(0)
    first = time.perf_counter() - t0
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        step(i)
        times.append(time.perf_counter() - t0)
    if device.type == "cuda":
        peak_mb = torch.cuda.max_memory_allocated() / 2**20
    else:
        peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base_rss) / 1024
    return StepTiming(first, statistics.median(times), peak_mb, warmup)
