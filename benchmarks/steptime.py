"""Time a training step (one warm-up, the median of repeated steps, peak memory), and run one
measured point in a fresh process.

Shared by the benchmark scripts beside it (run as ``python benchmarks/<script>.py``, which puts
this folder on ``sys.path``).
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["StepTiming", "run_point", "time_steps"]


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


def run_point(cmd: list[str], label: str, timeout: float, extra_path: tuple[str, ...] = ()):
    """Run one benchmark point in its own process; its last stdout line is a JSON row.

    Args:
        cmd: the child's argv. label: names the point in the lines printed on failure.
        timeout: seconds. extra_path: folders put before this process's ``sys.path``.

    Returns:
        The row (dict), or None when the child timed out or failed (said on stdout).
    """
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([*extra_path, *sys.path])}
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        print(f"{label}: timed out after {timeout} s", flush=True)
        return None
    if res.returncode != 0:
        print(f"{label}: failed ({res.returncode})\n{res.stderr[-3000:]}", flush=True)
        return None
    row = json.loads(res.stdout.strip().splitlines()[-1])
    print(json.dumps(row), flush=True)
    return row
