"""Why a checked planner drove as it did: each plan's choice in one episode, as a table.

``tools/drive.py ... planner=<bundle> trace=<scene>`` drives that scene once more with every
checked bundle planner recording its :class:`~renderworld.planning.PlanResult` s, and writes one
row per plan (every 0.5 s): the ego's speed, the candidate chosen (kind, lateral offset, target
speed or deceleration, score), the learned plan's own sub-scores (what it lost on when it was
replaced; where it was uncomfortable, the comfort quantity that went furthest beyond its bound,
as a multiple of it) and the acceleration the car then drove until the next plan. The episode is the
run's own (the loop is deterministic), so the trace explains the scores in the tables.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from renderworld.sim.closed_loop.episode import Episode, run_episode
from renderworld.sim.closed_loop.kinematics import SIM_DT

__all__ = ["trace_markdown", "trace_rows", "trace_scene", "write_trace"]

#: The learned plan's sub-scores a row reports, in the PDM score's order.
SUBSCORES = ("NC", "DAC", "EP", "TTC", "C")


def trace_scene(world, planner, limits=None, nudge_m: float = 0.0) -> tuple[Episode, list]:
    """Drive ``planner`` (a checked :class:`~renderworld.sim.closed_loop.BundlePlanner`)
    through ``world`` once, recording every plan, from the run's start (``nudge_m``:
    :func:`~renderworld.sim.closed_loop.episode.run_episode`).

    Returns:
        (the episode, [(t seconds, PlanResult)] in the order planned).

    Raises:
        ValueError: naming ``planner`` when it is not a checked bundle planner.
    """
    if not hasattr(planner, "results") or not getattr(planner, "check", False):
        raise ValueError(
            f"planner {getattr(planner, 'name', planner)!r}: only a checked bundle planner "
            "(check=True) records its candidates"
        )
    planner.results = []
    try:
        episode = run_episode(world, planner, limits, nudge_m=nudge_m)
        return episode, list(planner.results)
    finally:
        planner.results = None


def trace_rows(episode: Episode, results: list) -> list[dict]:
    """One dict per plan (module docstring).

    Args:
        episode: the traced episode (10 Hz states from its start).
        results: [(t, PlanResult)] of :func:`trace_scene`.

    Returns:
        Dicts with ``t`` (s), ``speed`` (m/s, at the plan), ``kind``, ``offset_m``, ``target``
        (the chosen candidate's target speed m/s or deceleration m/s^2), ``score``,
        ``plan_score`` and ``plan_<NC|DAC|EP|TTC|C>`` (the learned plan's), ``plan_comfort``
        (its worst comfort quantity and how far, a multiple of the bound; "" when comfortable
        or not recorded), ``accel_min``, ``accel_max`` (m/s^2 driven until the next plan)
        and ``yaw_rate_min``, ``yaw_rate_max`` (rad/s, left +, the same span: a heading rate
        that swings sign from plan to plan is a weave; NaN past the episode's end).
    """
    times = np.asarray(episode.times, dtype=np.float64)
    speed = np.asarray(episode.states, dtype=np.float64)[:, 3]
    accel = np.gradient(speed, SIM_DT) if len(speed) > 1 else np.zeros_like(speed)
    yaw = np.unwrap(np.asarray(episode.states, dtype=np.float64)[:, 2])
    yaw_rate = np.gradient(yaw, SIM_DT) if len(yaw) > 1 else np.zeros_like(yaw)
    rows = []
    for k, (t, result) in enumerate(results):
        c = result.candidates
        b = int(c.best)
        i = int(np.argmin(np.abs(times - t)))
        t_next = results[k + 1][0] if k + 1 < len(results) else times[-1]
        span = (times >= t - 1e-9) & (times < t_next - 1e-9)
        seg, turn = accel[span], yaw_rate[span]
        row = {
            "t": round(float(t - times[0]), 3),
            "speed": float(speed[i]),
            "kind": str(c.kind[b]),
            "offset_m": float(c.offset_m[b]),
            "target": float(c.speed[b]),
            "score": float(c.score[b]),
            "plan_score": float(c.score[0]),
            **{f"plan_{n}": float(getattr(c, n)[0]) for n in SUBSCORES},
            "plan_comfort": _worst_comfort(c),
            "accel_min": float(seg.min()) if len(seg) else float("nan"),
            "accel_max": float(seg.max()) if len(seg) else float("nan"),
            "yaw_rate_min": float(turn.min()) if len(turn) else float("nan"),
            "yaw_rate_max": float(turn.max()) if len(turn) else float("nan"),
        }
        rows.append(row)
    return rows


def _worst_comfort(c) -> str:
    """``"yaw_accel 1.8x"``: the learned plan's comfort quantity furthest beyond its bound."""
    if c.comfort_excess is None or float(c.comfort_excess[0]) < 1.0:
        return ""
    return f"{c.comfort_worst[0]} {float(c.comfort_excess[0]):.1f}x"


def trace_markdown(scene: str, planner: str, row: dict, rows: list[dict]) -> str:
    """The trace as markdown: the episode's scores (``row``, :func:`score_episode`'s dict),
    then one line per plan."""
    head = (f"### {scene}, {planner}: PDMS {row['PDMS']:.3f} (NC {row['NC']:.1f}, DAC "
            f"{row['DAC']:.0f}, EP {row['EP']:.3f}, TTC {row['TTC']:.0f}, C {row['C']:.0f}); "
            f"end: {row['end']}")  # fmt: skip
    lines = [
        head,
        "",
        "| t s | speed m/s | chosen | offset m | target | score | learned plan: score; NC DAC EP "
        "TTC C | driven accel m/s² | driven yaw rate rad/s |",
        "|---:|---:|---|---:|---:|---:|---|---|---|",
    ]
    for r in rows:
        plan = " ".join(f"{r[f'plan_{n}']:.2f}" if n == "EP" else f"{r[f'plan_{n}']:.0f}"
                        for n in SUBSCORES)  # fmt: skip
        lines.append(
            f"| {r['t']:.1f} | {r['speed']:.2f} | {r['kind']} | {r['offset_m']:+.0f} | "
            f"{r['target']:.2f} | {r['score']:.3f} | {r['plan_score']:.3f}; {plan}"
            f"{' (' + r['plan_comfort'] + ')' if r.get('plan_comfort') else ''} | "
            f"{r['accel_min']:+.1f} … {r['accel_max']:+.1f} | "
            f"{r['yaw_rate_min']:+.2f} … {r['yaw_rate_max']:+.2f} |"
        )
    lines += ["", "target: the chosen candidate's target speed (m/s), or its deceleration (m/s², "
              "kind brake); the learned plan's sub-scores say what it lost on where another was "
              "chosen, and in brackets the comfort quantity it broke (a multiple of NAVSIM's "
              "bound); driven: from this plan to the next (yaw rate left +)."]  # fmt: skip
    return "\n".join(lines) + "\n"


def write_trace(world, planners: list, out: Path, limits=None, nudge_m: float = 0.0) -> Path:
    """Trace ``world`` with every checked bundle planner of ``planners`` from the run's start
    (``nudge_m``); write ``out/trace_<scene>.md`` and return its path.

    Raises:
        ValueError: naming ``trace`` when none of ``planners`` is a checked bundle planner.
    """
    from renderworld.sim.closed_loop.scores import score_episode

    checked = [p for p in planners if hasattr(p, "results") and getattr(p, "check", False)]
    if not checked:
        raise ValueError(f"trace={world.name}: no checked planner to trace; pass planner=<bundle>")
    parts = []
    for p in checked:
        episode, results = trace_scene(world, p, limits, nudge_m)
        parts.append(trace_markdown(world.name, p.name, score_episode(world, episode),
                                    trace_rows(episode, results)))  # fmt: skip
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"trace_{world.name}.md"
    path.write_text(f"# Trace of {world.name}\n\n" + "\n".join(parts))
    return path
