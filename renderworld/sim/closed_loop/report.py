"""Closed-loop outputs: tables (markdown, CSV, JSON) and one bird's-eye picture per behaviour.

Files written into the output folder by :func:`write_outputs`:

* ``closed_loop.json``: every row, the aggregates (all scenes and per behaviour), timings,
  the planners (privileged or not), the run's settings and the self-check.
* ``closed_loop.csv``: one row per (planner, scene): every score and count of
  :func:`~renderworld.sim.closed_loop.scores.score_episode`, ``EP_best`` and ``PDMS_best``
  (:func:`~renderworld.sim.closed_loop.scores.add_best_progress`) and one ``comfort_<quantity>``
  column per comfort bound.
* ``closed_loop.md``: the summary table, the per-behaviour table, timings (EP and PDMS against
  the log; ``EP_best`` and ``PDMS_best`` are in the CSV and JSON rows only).
* ``figures/closed_loop_<behaviour>.png``: the first scene of each behaviour, bird's-eye view
  (scene frame): road, the logged ego path, each planner's driven path, the objects at the
  moment of the first collision (or at the scene end), the collision point.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from renderworld.sim.closed_loop.boxes import EGO_HALF, SceneBoxes
from renderworld.sim.closed_loop.runner import ClosedLoopRun
from renderworld.sim.closed_loop.scores import SCORE_KEYS
from renderworld.sim.layout import World, ego_box_at

__all__ = ["summary_markdown", "write_outputs", "behaviour_figure"]

_COUNTS = ("at_fault_collisions", "off_road", "ttc_violations", "comfort_violations", "failures")


def _label(run: ClosedLoopRun, name: str) -> str:
    return f"{name} (privileged)" if run.planners.get(name, {}).get("privileged") else name


def summary_markdown(run: ClosedLoopRun) -> str:
    """The summary table (all scenes), the per-behaviour table and the timing table."""
    n = next(iter(run.summary.values()))["episodes"]
    head = "| planner | " + " | ".join(SCORE_KEYS) + " | at-fault collisions | off road | "
    head += "TTC < 1 s | comfort | planner failures |"
    lines = [head, "|---" * (len(SCORE_KEYS) + 6) + "|"]
    for name, s in run.summary.items():
        cells = [f"{s[k]:.3f}" for k in SCORE_KEYS] + [f"{s[k]}/{n}" for k in _COUNTS]
        lines.append(f"| {_label(run, name)} | " + " | ".join(cells) + " |")
    keys = " | ".join(SCORE_KEYS)
    beh = [f"| planner | behaviour | scenes | {keys} | at-fault collisions |",
           "|---" * (len(SCORE_KEYS) + 4) + "|"]  # fmt: skip
    for name, per in run.by_behaviour.items():
        for b, s in per.items():
            cells = " | ".join(f"{s[k]:.3f}" for k in SCORE_KEYS)
            beh.append(
                f"| {name} | {b} | {s['episodes']} | {cells} | "
                f"{s['at_fault_collisions']}/{s['episodes']} |"
            )
    tim = ["| planner | plans | wall s | voxelise ms/plan | plan ms/plan | simulate ms/plan |",
           "|---|---|---|---|---|---|"]  # fmt: skip
    for name, t in run.timing.items():
        tim.append(
            f"| {name} | {t['steps']} | {t['seconds']:.1f} | {t['voxelise_ms']:.1f} | "
            f"{t['plan_ms']:.1f} | {t['sim_ms']:.1f} |"
        )
    return "\n".join(
        ["Scores (mean over scenes) and counts (scenes with the event / scenes):", "", *lines, "",
         "Per behaviour:", "", *beh, "", "Time per plan (0.5 s of driving):", "", *tim]
    )  # fmt: skip


def _rect(ax, c, yaw, half, **kw):
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-np.sin(yaw), np.cos(yaw)])
    corners = [c + a * half[0] * u + b * half[1] * v for a, b in ((1, 1), (1, -1), (-1, -1),
                                                                  (-1, 1), (1, 1))]  # fmt: skip
    ax.plot(*np.array(corners).T, **kw)


def behaviour_figure(world: World, episodes: list, out_png: Path) -> Path:
    """Bird's-eye picture of one scene driven by several planners (module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    boxes = SceneBoxes(world)
    log_xy = world.ego.trajectory.pose(np.arange(0.0, world.duration + 1e-9, 0.1))[0]
    every = np.concatenate([log_xy] + [e.states[:, :2] for e in episodes])
    lo, hi = every.min(0) - 15.0, every.max(0) + 15.0
    r = world.raster
    i0, i1 = np.clip(((np.array([lo[0], hi[0]]) - r.x0) / r.cell).astype(int), 0, r.shape[0])
    j0, j1 = np.clip(((np.array([lo[1], hi[1]]) - r.y0) / r.cell).astype(int), 0, r.shape[1])
    fig, ax = plt.subplots(figsize=(9, 5.5))
    road = (r.classes[i0:i1, j0:j1] == 24).T
    ax.imshow(np.where(road, 0.85, 0.55), cmap="gray", vmin=0, vmax=1, origin="lower",
              extent=(r.x0 + i0 * r.cell, r.x0 + i1 * r.cell, r.y0 + j0 * r.cell,
                      r.y0 + j1 * r.cell))  # fmt: skip
    ax.plot(*log_xy.T, "k--", lw=1.5, label="logged ego")
    colours = plt.get_cmap("tab10")
    t_show = world.duration
    for n, e in enumerate(episodes):
        col = colours(n % 10)
        tag = f"{e.planner}: {e.end}" + (f" ({e.contact.key})" if e.contact else "")
        ax.plot(*e.states[:, :2].T, "-", color=col, lw=2, label=tag)
        x, y, yaw, _ = e.states[-1]
        c, yy = ego_box_at(np.array([x, y]), yaw)
        _rect(ax, c, yy, EGO_HALF, color=col, lw=1.5)
        if e.end == "collision":
            ax.plot(*c, "x", color="red", ms=12, mew=3)
            t_show = min(t_show, float(e.times[-1]))
    c, yy = boxes.at(t_show)
    near = (c[:, 0] > lo[0]) & (c[:, 0] < hi[0]) & (c[:, 1] > lo[1]) & (c[:, 1] < hi[1])
    for i in np.flatnonzero(near & boxes.moving):
        key = boxes.keys[i]
        _rect(ax, c[i], yy[i], boxes.half[i], color="crimson" if key.startswith("scn_") else
              "dimgray", lw=1.2)  # fmt: skip
    for i in np.flatnonzero(near & ~boxes.moving & (boxes.half.max(1) < 6)):
        _rect(ax, c[i], yy[i], boxes.half[i], color="saddlebrown", lw=0.8)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_title(f"{world.name}: {world.spec.behaviour} (objects at t = {t_show:.1f} s; "
                 "red = the scripted agent, x = collision)", fontsize=9)  # fmt: skip
    ax.legend(fontsize=7, loc="upper left")
    ax.set_xlabel("x (m, scene frame)")
    ax.set_ylabel("y (m)")
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=90)
    plt.close(fig)
    return out_png


def write_outputs(
    run: ClosedLoopRun, worlds: list[World], out: Path, settings: dict, check: list[str]
) -> dict[str, Path]:
    """Write the JSON, CSV, markdown tables and the pictures (module docstring) into ``out``.

    Returns:
        ``{"json", "csv", "md"}`` paths and ``figures/<behaviour>`` paths.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = {
        "settings": settings,
        "planners": run.planners,
        "summary": run.summary,
        "by_behaviour": run.by_behaviour,
        "timing": run.timing,
        "self_check": {"log_replay_failures": check},
        "rows": run.rows,
    }
    paths = {"json": out / "closed_loop.json", "csv": out / "closed_loop.csv",
             "md": out / "closed_loop.md"}  # fmt: skip
    paths["json"].write_text(json.dumps(data, indent=1, sort_keys=True))
    flat = [
        {k: v for k, v in r.items() if k != "comfort_steps"}
        | {f"comfort_{k}": v for k, v in r["comfort_steps"].items()}
        for r in run.rows
    ]
    with open(paths["csv"], "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(flat[0]))
        w.writeheader()
        w.writerows(flat)
    paths["md"].write_text(summary_markdown(run) + "\n")
    by_name = {w.name: w for w in worlds}
    seen = {}
    for e in run.episodes:
        seen.setdefault(e.behaviour, e.scene)
    for beh, scene in seen.items():
        eps = [e for e in run.episodes if e.scene == scene]
        png = out / "figures" / f"closed_loop_{beh}.png"
        paths[f"figures/{beh}"] = behaviour_figure(by_name[scene], eps, png)
    return paths
