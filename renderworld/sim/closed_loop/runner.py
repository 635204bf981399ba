"""Run planners over scenes in closed loop: episodes, scores, aggregates, timings, self-check.

The log-replay planner proves the runner: on every scene it must end at the scene's end with
no collision, full drivable-area compliance and progress 1 (:func:`self_check`). After every
planner drove, each row gets ``EP_best`` and ``PDMS_best``: progress over the best
collision-free, on-road episode of its scene in the run, NAVSIM's reference
(:func:`~renderworld.sim.closed_loop.scores.add_best_progress`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from renderworld.sim.closed_loop.boxes import SceneBoxes
from renderworld.sim.closed_loop.episode import Episode, run_episode
from renderworld.sim.closed_loop.kinematics import KinematicLimits
from renderworld.sim.closed_loop.observe import OccupancyRenderer
from renderworld.sim.closed_loop.scores import add_best_progress, aggregate, score_episode
from renderworld.sim.layout import World

__all__ = ["ClosedLoopRun", "run_closed_loop", "self_check"]


@dataclass
class ClosedLoopRun:
    """Everything a run produced.

    Attributes:
        rows: per (planner, scene) scores (:func:`score_episode`), planners in the given order,
            each with ``EP_best`` and ``PDMS_best`` (:func:`add_best_progress`, over all of
            the run's rows).
        episodes: the matching :class:`Episode` s (states for the pictures).
        summary: ``{planner: aggregate}`` over all scenes.
        by_behaviour: ``{planner: {behaviour: aggregate}}``.
        timing: ``{planner: {"seconds", "steps", "voxelise_ms", "plan_ms", "sim_ms"}}``: wall
            time, plans made, and milliseconds per plan spent voxelising, planning and in the
            rest of the step (tracking, collision and road checks).
        planners: ``{name: {"privileged": bool}}``.
    """

    rows: list = field(default_factory=list)
    episodes: list = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    by_behaviour: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)
    planners: dict = field(default_factory=dict)


def run_closed_loop(
    worlds: list[World],
    planners: list,
    limits: KinematicLimits | None = None,
    progress=True,
    nudge_m: float = 0.0,
) -> ClosedLoopRun:
    """Drive every planner through every world, score the episodes, then add ``EP_best``.

    Args:
        worlds: generated scenes (:func:`renderworld.sim.build_worlds`).
        planners: planner objects (:mod:`renderworld.sim.closed_loop.planners`).
        limits: the car's limits.
        progress: a tqdm bar over episodes.
        nudge_m: every episode starts this far ahead of the log (:func:`run_episode`).

    Raises:
        ValueError: no worlds or planners, two planners with one name, or a scene too short.
    """
    if not worlds:
        raise ValueError("worlds: expected at least one scene, got none")
    if not planners:
        raise ValueError("planners: expected at least one planner, got none")
    names = [p.name for p in planners]
    if len(set(names)) != len(names):
        raise ValueError(f"planners: expected distinct names, got {names}")
    run = ClosedLoopRun()
    boxes = [SceneBoxes(w) for w in worlds]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(worlds) * len(planners), desc="driving", unit="episode")
    for p in planners:
        run.planners[p.name] = {"privileged": bool(getattr(p, "privileged", False))}
        renderer = getattr(p, "observer", None)  # what it sees through (cameras), else GT
        if renderer is None and getattr(p, "grid", None) is not None:
            renderer = OccupancyRenderer(p.grid)
        t0 = time.perf_counter()
        eps: list[Episode] = []
        for w, b in zip(worlds, boxes):
            eps.append(run_episode(w, p, limits, renderer, b, nudge_m))
            if bar is not None:
                bar.set_postfix_str(f"{p.name} {w.name}")
                bar.update(1)
        seconds = time.perf_counter() - t0
        rows = [score_episode(w, e, b) for w, e, b in zip(worlds, eps, boxes)]
        run.rows += rows
        run.episodes += eps
        run.summary[p.name] = aggregate(rows)
        run.by_behaviour[p.name] = {
            beh: aggregate([r for r in rows if r["behaviour"] == beh])
            for beh in dict.fromkeys(r["behaviour"] for r in rows)
        }
        steps = sum(len(e.plan_ms) for e in eps)
        vox = sum(sum(e.voxelise_ms) for e in eps)
        plan = sum(sum(e.plan_ms) for e in eps)
        run.timing[p.name] = {
            "seconds": round(seconds, 3),
            "steps": steps,
            "voxelise_ms": round(vox / max(steps, 1), 3),
            "plan_ms": round(plan / max(steps, 1), 3),
            "sim_ms": round((1e3 * seconds - vox - plan) / max(steps, 1), 3),
        }
    if bar is not None:
        bar.close()
    add_best_progress(run.rows)  # every planner's episodes: the best one per scene
    return run


#: How far below 1 log replay's EP may read: the tracked log ends within millimetres of the
#: logged one (a car stopping mid-turn), and EP keeps 6 digits.
EP_TOLERANCE = 1e-4


def self_check(run: ClosedLoopRun, planner: str = "log_replay") -> list[str]:
    """Scenes where ``planner`` (log replay) is not perfect: [] when it is (or did not run).

    Perfect: ends at the scene's end, no collision, DAC 1, EP 1 within :data:`EP_TOLERANCE`.
    """
    bad = []
    for r in run.rows:
        if r["planner"] != planner:
            continue
        if (
            r["end"] != "scene_end"
            or r["collision"]
            or r["DAC"] != 1.0
            or r["EP"] < 1.0 - EP_TOLERANCE
        ):
            bad.append(
                f"{r['scene']} ({r['behaviour']}): end {r['end']} {r['collided_with']}, "
                f"DAC {r['DAC']:g}, EP {r['EP']:.6f}"
            )
    return bad
