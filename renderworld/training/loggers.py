"""Metric logging: ``metrics.csv`` in the run directory and, when installed, TensorBoard.

``metrics.csv`` is long ("tidy") and append-only, one row per value: ``step,epoch,key,value``.
Appending never rewrites earlier rows, so a killed run loses at most its last line; read it
with ``pandas.read_csv(...).pivot_table(index="step", columns="key", values="value")``.
Only rank 0 logs; other ranks get a logger that drops everything.
"""

from __future__ import annotations

import csv
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["MetricLogger", "MetricWindow", "truncate_metrics_csv", "CSV_HEADER"]

log = logging.getLogger("renderworld.training")

CSV_HEADER = ("step", "epoch", "key", "value")


class MetricLogger:
    """Write scalar metrics to CSV and TensorBoard (rank 0 only).

    Args:
        run_dir: Run directory; ``metrics.csv`` and ``tb/`` go there.
        enabled: False on ranks other than 0: every call is a no-op.
        tensorboard: Try TensorBoard (skipped with a log line when it is not installed).
    """

    def __init__(self, run_dir: str | os.PathLike, enabled: bool = True, tensorboard: bool = True):
        self.enabled = enabled
        self.path = Path(run_dir) / "metrics.csv"
        self._file = None
        self._writer = None
        self._tb = None
        if not enabled:
            return
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._file = open(self.path, "a", newline="")  # noqa: SIM115 - closed in close()
        self._writer = csv.writer(self._file)
        if new:
            self._writer.writerow(CSV_HEADER)
            self._file.flush()
        if tensorboard:
            self._tb = _make_tensorboard(Path(run_dir) / "tb")

    def log(self, metrics: Mapping[str, Any], step: int, epoch: int = 0) -> None:
        """Log scalar ``metrics`` at ``step``; non-finite values are written as nan / inf."""
        if not self.enabled or self._writer is None:
            return
        for key, value in metrics.items():
            v = float(value)
            self._writer.writerow((int(step), int(epoch), key, repr(v)))
            if self._tb is not None:
                self._tb.add_scalar(key, v, global_step=int(step))
        self._file.flush()  # type: ignore[union-attr]
        if self._tb is not None:
            self._tb.flush()

    def close(self) -> None:
        """Flush and close files."""
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._tb is not None:
            self._tb.close()
            self._tb = None


def truncate_metrics_csv(path: str | os.PathLike, max_step: int) -> int:
    """Drop rows logged after ``max_step`` (and torn lines), rewriting the file atomically.

    Used on resume: rows written by the interrupted run after its last checkpoint would
    otherwise appear twice.

    Returns:
        Number of rows dropped.
    """
    path = Path(path)
    if not path.exists():
        return 0
    kept: list[list[str]] = []
    dropped = 0
    with open(path, newline="") as f:
        for i, row in enumerate(csv.reader(f)):
            if i == 0 and tuple(row) == CSV_HEADER:
                continue
            try:
                ok = len(row) == len(CSV_HEADER) and int(row[0]) <= max_step
                float(row[3]) if ok else None
            except ValueError:
                ok = False
            if ok:
                kept.append(row)
            else:
                dropped += 1
    if dropped:
        tmp = path.with_name(f".{path.name}.tmp")
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(CSV_HEADER)
            w.writerows(kept)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    return dropped


def _make_tensorboard(directory: Path) -> Any:
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        log.info("TensorBoard not installed: logging to metrics.csv only")
        return None
    return SummaryWriter(log_dir=str(directory))


class MetricWindow:
    """Per-step loss sums between two logged steps (tensors, so ranks reduce them once).

    ``last`` holds the means of the last logged window.
    """

    def __init__(self) -> None:
        self.last: dict[str, float] = {}
        self.reset({})

    def reset(self, last: dict[str, float]) -> None:
        self.sums: dict[str, Any] = {}
        self.steps, self.t0 = 0, time.monotonic()
        self.last = last or self.last

    def add(self, sums: Mapping[str, Any]) -> None:
        for k, v in sums.items():
            self.sums[k] = self.sums.get(k, 0) + v
        self.steps += 1
