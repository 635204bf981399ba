"""How long a sweep will take, printed before it starts.

Each training point costs ``POINT_S[kind]`` (process start, data, final evaluation, inference
timing) plus its steps times ``STEP_S[kind]``, and ``LIBRARY_S`` + steps times
``LIBRARY_STEP_S`` more when it trains on the scenario library; a planner point costs
``PLANNER_POINT_S[grid]``. The figures are **CPU seconds** of one-thread points of the quick and
standard presets, measured two at a time on the 2-core CPU the presets are sized for
(``MEASURED``): with ``jobs`` points at a time on a machine that runs nothing else the wall time
is about the CPU time over ``jobs``; on a shared one it grows with the others' load
(``LOADED_WALL_PER_CPU`` was measured beside other jobs). Points already measured in the output
folder (same fingerprint) count their recorded wall time."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from renderworld.bench.sweep import BenchPoint, point_fingerprint

__all__ = ["MEASURED", "STEP_S", "POINT_S", "LIBRARY_S", "LIBRARY_STEP_S",
           "PLANNER_POINT_S", "KNOB_FACTOR",
           "LOADED_WALL_PER_CPU", "point_seconds", "estimate", "estimate_text"]  # fmt: skip

#: Where and when the figures below were measured.
MEASURED = (
    "CPU seconds of the points of bench=quick and bench=standard, 2026-11-26, commit 89ae1a7, "
    "2 points at a time on a 2-core Zen 4 CPU that ran nothing else"
)
#: CPU seconds per optimizer step, 1 torch thread: the slope between the quick and the standard
#: budget of the same point (tokenizer 40 -> 250 steps, Img2Occ 40 -> 200, world model
#: 20 -> 400); the world model's without the scenario library (its per-step share below).
STEP_S = {"tokenizer": 0.33, "img2occ": 0.38, "world_model/pose_warp": 0.67,
          "world_model/tokens": 0.48}  # fmt: skip
#: CPU seconds per point besides its steps (process start, data, the final evaluation on
#: mini_val, Img2Occ's threshold search on 24 samples, inference timing); the pose-warp world
#: model's includes its experiment's pose warm-up (3200 pose-only steps: 85 s alone with the
#: scenario library, frame cache warm, measured 2026-11-26 after the runs above) and its mover
#: head's fit (1500 steps and the tracks they read: ~60 s, 2026-11-27).
POINT_S = {"tokenizer": 7.0, "img2occ": 76.0, "world_model/pose_warp": 170.0,
           "world_model/tokens": 12.0}  # fmt: skip
#: Extra CPU seconds of a world-model point that trains on the scenario library: once (its
#: windows' frames read and encoded) and per step (more frames to load).
LIBRARY_S = 32.0
LIBRARY_STEP_S = 0.1
#: CPU seconds of one planner point per grid (7 windows; occ3d: untrained paper-sized models).
PLANNER_POINT_S = {"mini": 6.0, "occ3d": 99.0}
#: Per-step cost of a knob value relative to the stage default's (grid: from the 8a2fb97 quick
#: run's train-time ratios; the others measured by the standard run).
KNOB_FACTOR = {("img2occ", "grid", "quarter"): 1.2, ("img2occ", "grid", "half"): 4.0,
               ("img2occ", "input_size", "[64, 112]"): 0.7,
               ("img2occ", "fine_semantics", "False"): 0.75}  # fmt: skip
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
        seconds += LIBRARY_S + steps * LIBRARY_STEP_S
    return seconds


def estimate(points: Sequence[BenchPoint], out: Path, infer_frames: int) -> dict[str, float]:
    """``{"total_s", "left_s", "left_alone_s", "done"}``: the sweep's estimated seconds, those
    still to run (``left_alone_s`` of them planner points, which run one at a time), and how many
    points ``out`` already holds (their recorded time counts)."""
    total = left = alone = 0.0
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
        alone += s if p.stage == "planner" else 0.0
    return {"total_s": total, "left_s": left, "left_alone_s": alone, "done": float(done)}


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
        left = (est["left_s"] - est["left_alone_s"]) / jobs + est["left_alone_s"]
        wall = f"; {jobs} points at a time: about {left / 60:.0f} min of wall time left"
    return (
        f"estimate: {est['total_s'] / 60:.0f} min of points in all ({per} min), "
        f"{est['left_s'] / 60:.0f} min left ({int(est['done'])} of {len(points)} points "
        f"already measured) on a machine that runs nothing else{wall}; {lo:g}-{hi:g}x that "
        f"beside other jobs (per-step {MEASURED})"
    )
