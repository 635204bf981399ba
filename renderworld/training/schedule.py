"""The schedule record of a training run: the step it reached of the steps it was given.

Schedules are step counts, so a run's results do not depend on the machine's speed;
``trainer.max_minutes`` is only a guard. ``schedule.json`` in the run dir says whether the guard
fired, so a report can say "stopped at step N of M" instead of passing the figures off as those of
the full schedule. Stdlib only: the main job reads it without importing torch.
"""

from __future__ import annotations

import json
from pathlib import Path

from renderworld.data.atomic import atomic_write

__all__ = ["SCHEDULE_FILE", "read_schedule", "write_schedule"]

SCHEDULE_FILE = "schedule.json"


def write_schedule(
    run_dir: str | Path,
    step: int,
    max_steps: int,
    stopped_early: bool,
    max_minutes: float | None,
    elapsed_s: float,
) -> Path:
    """Write ``<run_dir>/schedule.json`` atomically.

    Args:
        run_dir: the training run's folder.
        step: optimizer steps done.
        max_steps: optimizer steps scheduled.
        stopped_early: whether the wall-clock guard stopped the run before ``max_steps``.
        max_minutes: the guard, minutes (None: no guard).
        elapsed_s: training seconds summed over resumed segments.
    """
    record = {
        "step": int(step),
        "max_steps": int(max_steps),
        "stopped_early": bool(stopped_early),
        "max_minutes": max_minutes,
        "elapsed_s": round(float(elapsed_s), 3),
    }
    text = json.dumps(record, indent=2) + "\n"
    return atomic_write(Path(run_dir) / SCHEDULE_FILE, lambda tmp: Path(tmp).write_text(text))


def read_schedule(run_dir: str | Path) -> dict | None:
    """The schedule record of a run dir, or None when it has none (not a training run).

    Raises:
        ValueError: the file exists but is not a schedule record (names the file).
    """
    path = Path(run_dir) / SCHEDULE_FILE
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        int(record["step"]), int(record["max_steps"]), bool(record["stopped_early"])
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a schedule record ({err})") from None
    return record
