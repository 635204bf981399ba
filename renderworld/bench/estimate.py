"""How long a sweep will take, printed before it starts.

Each training point costs ``POINT_S[kind]`` (process start, data, final evaluation, inference
timing) plus its steps times ``STEP_S[kind]``, scaled by ``KNOB_FACTOR`` for the knob values
measured to cost more per step; a planner point costs ``PLANNER_POINT_S[grid]``. These were
measured on the 2-core CPU the presets are sized for, one torch thread, while the machine was
shared (load average 2-4): see ``MEASURED``. Points already measured in the output folder (same
fingerprint) count their own recorded time.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from renderworld.bench.sweep import BenchPoint, point_fingerprint

__all__ = ["MEASURED", "STEP_S", "POINT_S", "PLANNER_POINT_S", "KNOB_FACTOR", "point_seconds",
           "estimate", "estimate_text"]  # fmt: skip

#: Where and when the figures below were measured.
MEASURED = "2026-11-26, commit bfac6fe + the sweep's changes, 2-core AVX2 CPU shared (load 2-4)"
#: Seconds per optimizer step, 1 torch thread (tokenizer_mini, img2occ_mini with its sample
#: cache's first epoch included, world_model_mini per forecaster).
STEP_S = {"tokenizer": 0.6, "img2occ": 0.4, "world_model/pose_warp": 0.5, "world_model/tokens": 0.5}
#: Seconds per point besides the steps.
POINT_S = {"tokenizer": 20.0, "img2occ": 60.0, "world_model/pose_warp": 60.0,
           "world_model/tokens": 60.0}  # fmt: skip
#: Extra seconds of a world-model point that trains on the scenario library (its windows'
#: frames are read and encoded once).
LIBRARY_S = 60.0
#: Seconds of one planner point per grid.
PLANNER_POINT_S = {"mini": 40.0, "occ3d": 120.0}
#: Per-step cost of a knob value relative to the stage default's (those measured to differ).
KNOB_FACTOR = {("img2occ", "grid", "quarter"): 1.5, ("img2occ", "grid", "half"): 4.0}


def _last(overrides: Sequence[str], key: str) -> str | None:
    values = [o.split("=", 1)[1] for o in overrides if o.startswith(key + "=")]
    return values[-1] if values else None


def point_seconds(point: BenchPoint) -> float:
    """Estimated seconds of one point (see the module docstring)."""
    if point.stage == "planner":
        return PLANNER_POINT_S["occ3d" if _last(point.overrides, "grid") == "occ3d" else "mini"]
    kind = point.stage
    if kind == "world_model":
        forecaster = _last(point.overrides, "stage.forecaster") or "pose_warp"
        kind = f"world_model/{forecaster}"
    steps = int(_last(point.overrides, "trainer.max_steps") or 0)
    factor = KNOB_FACTOR.get((point.stage, point.knob, str(point.value)), 1.0)
    seconds = POINT_S[kind] + steps * STEP_S[kind] * factor
    library = _last(point.overrides, "stage.extra_train_roots")
    if library not in (None, "[]"):
        seconds += LIBRARY_S
    return seconds


def estimate(points: Sequence[BenchPoint], out: Path, infer_frames: int) -> dict[str, float]:
    """``{"total_s", "left_s", "done"}``: the sweep's estimated seconds, those still to run, and
    how many points ``out`` already holds (their recorded time counts)."""
    total = left = 0.0
    done = 0
    for p in points:
        stored = Path(out) / "points" / p.point_id / "result.json"
        if stored.is_file():
            res = json.loads(stored.read_text())
            if res.get("fingerprint") == point_fingerprint(p, infer_frames):
                total += float(res.get("point_wall_s", point_seconds(p)))
                done += 1
                continue
        s = point_seconds(p)
        total += s
        left += s
    return {"total_s": total, "left_s": left, "done": float(done)}


def estimate_text(points: Sequence[BenchPoint], out: Path, infer_frames: int) -> str:
    """One line: the estimate per stage and in all (minutes)."""
    est = estimate(points, out, infer_frames)
    stages: dict[str, float] = {}
    for p in points:
        key = p.stage + (" (ranking)" if p.phase else "")
        stages[key] = stages.get(key, 0.0) + point_seconds(p)
    per = ", ".join(f"{k} {v / 60:.0f}" for k, v in stages.items())
    return (
        f"estimate: {est['total_s'] / 60:.0f} min in all ({per} min), "
        f"{est['left_s'] / 60:.0f} min left ({int(est['done'])} of {len(points)} points "
        f"already measured); per-step times of {MEASURED}"
    )
