"""How long a sweep will take, printed before it starts.

Each training point costs ``POINT_S[kind]`` (process start, data, final evaluation, inference
timing) plus its steps times ``STEP_S[kind]``, and ``LIBRARY_S`` more when it trains on the
scenario library; a planner point costs ``PLANNER_POINT_S[grid]``. The figures are **CPU
seconds** of one-thread points measured with ``benchmarks/sweep_step_times.py`` on the 2-core
CPU the presets are sized for (``MEASURED``): on a machine that runs nothing else a one-thread
point's wall time is close to its CPU time; on a shared one its wall time grows with the
others' load (``LOADED_WALL_PER_CPU`` was measured beside other jobs). Points already measured
in the output folder (same fingerprint) count their recorded wall time.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from renderworld.bench.sweep import BenchPoint, point_fingerprint

__all__ = ["MEASURED", "STEP_S", "POINT_S", "LIBRARY_S", "PLANNER_POINT_S", "KNOB_FACTOR",
           "LOADED_WALL_PER_CPU", "point_seconds", "estimate", "estimate_text"]  # fmt: skip

#: Where and when the figures below were measured.
MEASURED = (
    "CPU seconds measured 2026-11-26 at commit 471fa24 on the 2-core CPU while it ran other jobs "
    "(load average 6-7)"
)
#: CPU seconds per optimizer step, 1 torch thread: tokenizer_mini 0.36 and world_model_mini
#: (pose_warp) 0.85 measured (``benchmarks/sweep_step_times.py --steps 5 20``); the token
#: forecaster is taken as the pose-warp one's and Img2Occ's from its documented 0.22 s a step
#: at 2 threads (docs/experiments.md), both not measured here.
STEP_S = {"tokenizer": 0.36, "img2occ": 0.4, "world_model/pose_warp": 0.85,
          "world_model/tokens": 0.85}  # fmt: skip
#: CPU seconds per point besides its steps (process start, data, the final evaluation on
#: mini_val, Img2Occ's threshold search, inference timing): measured for the tokenizer (6.8),
#: Img2Occ (237 at 5 steps) and the pose-warp world model (29.6).
POINT_S = {"tokenizer": 6.8, "img2occ": 230.0, "world_model/pose_warp": 29.6,
           "world_model/tokens": 29.6}  # fmt: skip
#: Extra CPU seconds of a world-model point that trains on the scenario library (its windows'
#: frames are read and encoded once): not measured here (no library on the measuring machine).
LIBRARY_S = 60.0
#: CPU seconds of one planner point per grid: mini measured (6.4, 7 windows); occ3d not.
PLANNER_POINT_S = {"mini": 6.4, "occ3d": 60.0}
#: Per-step cost of a knob value relative to the stage default's (not measured: from the
#: 8a2fb97 quick run's train-time ratios, docs/experiments.md).
KNOB_FACTOR = {("img2occ", "grid", "quarter"): 1.2, ("img2occ", "grid", "half"): 4.0}
#: Wall seconds per CPU second of a point measured while the machine ran other jobs (load
#: average 6-7): 5.4 (Img2Occ) to 13 (tokenizer). On a machine that runs nothing else, ~1.
LOADED_WALL_PER_CPU = (5.4, 13.0)


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


def estimate_text(points: Sequence[BenchPoint], out: Path, infer_frames: int, jobs: int = 1) -> str:
    """One line: the estimate per stage and in all (minutes of one-at-a-time points; with
    ``jobs`` > 1 the wall time left is taken as the training points' time over ``jobs``)."""
    est = estimate(points, out, infer_frames)
    stages: dict[str, float] = {}
    for p in points:
        key = p.stage + (" (ranking)" if p.phase else "")
        stages[key] = stages.get(key, 0.0) + point_seconds(p)
    per = ", ".join(f"{k} {v / 60:.0f}" for k, v in stages.items())
    lo, hi = LOADED_WALL_PER_CPU
    wall = ""
    if jobs > 1:
        alone = sum(point_seconds(p) for p in points if p.stage == "planner")
        left = max(est["left_s"] - alone, 0.0) / jobs + min(alone, est["left_s"])
        wall = f"; {jobs} points at a time: about {left / 60:.0f} min of wall time left"
    return (
        f"estimate: {est['total_s'] / 60:.0f} min of points in all ({per} min), "
        f"{est['left_s'] / 60:.0f} min left ({int(est['done'])} of {len(points)} points "
        f"already measured) on a machine that runs nothing else{wall}; {lo:g}-{hi:g}x that "
        f"beside other jobs (per-step {MEASURED})"
    )
