"""Closed-loop scores of an episode, NAVSIM-style, and their aggregates per behaviour.

Per episode (0/1 unless said), from the 10 Hz states:

* ``NC`` (no at-fault collision): 0 when the ego box overlapped an object's box and the object
  did not come from behind (:class:`~renderworld.sim.closed_loop.boxes.Contact`).
* ``DAC`` (drivable-area compliance): 0 when a corner or edge midpoint of the ego box left the
  driveable surface.
* ``EP`` (ego progress, in [0, 1]): arc length driven along the logged ego's path (the route;
  :func:`route_progress`: nothing counts while the ego is more than 4 m off it) over the
  logged ego's over the same time (start to scene end, 10 Hz), clipped to [0, 1], rounded to
  1e-6; 1 when the logged ego moves less than 5 m.
* ``TTC``: 0 when at some step, with the ego moving (> 0.1 m/s), the ego box extrapolated at
  constant velocity and heading overlaps within 1 s an object (ahead of the ego box centre)
  extrapolated at its constant velocity.
* ``C`` (comfort): 0 when a bound is exceeded at some step (NAVSIM's bounds): longitudinal
  acceleration in [-4.05, 2.40] m/s^2, |lateral acceleration| <= 4.89 m/s^2, |longitudinal
  jerk| <= 4.13 m/s^3, |yaw rate| <= 0.95 rad/s, |yaw acceleration| <= 1.93 rad/s^2; speed and
  yaw are smoothed over 0.5 s (5 samples) before differencing.
* ``PDMS = NC x DAC x (5 TTC + 5 EP + 2 C) / 12`` (NAVSIM's PDM score with the multipliers and
  weights it uses); 0 for an episode the planner failed (``planner_error``).
"""

from __future__ import annotations

import numpy as np

from renderworld.sim.agents import Path, rects_overlap
from renderworld.sim.closed_loop.boxes import EGO_HALF, SceneBoxes
from renderworld.sim.closed_loop.episode import Episode
from renderworld.sim.closed_loop.kinematics import SIM_DT
from renderworld.sim.layout import World, ego_box_at

__all__ = [
    "COMFORT_BOUNDS",
    "ROUTE_TOLERANCE",
    "SCORE_KEYS",
    "aggregate",
    "pdms",
    "route_progress",
    "score_episode",
]

#: (low, high) of each comfort quantity (NAVSIM's bounds).
COMFORT_BOUNDS = {
    "lon_accel": (-4.05, 2.40),
    "lat_accel": (-4.89, 4.89),
    "lon_jerk": (-4.13, 4.13),
    "yaw_rate": (-0.95, 0.95),
    "yaw_accel": (-1.93, 1.93),
}
SCORE_KEYS = ("NC", "DAC", "EP", "TTC", "C", "PDMS")
_TTC_HORIZON = 1.0
_MIN_LOGGED_PROGRESS = 5.0
#: Farther than this from the route (metres), the ego makes no progress along it.
ROUTE_TOLERANCE = 4.0


def pdms(nc: float, dac: float, ep: float, ttc: float, c: float) -> float:
    """NC x DAC x (5 TTC + 5 EP + 2 C) / 12."""
    return nc * dac * (5 * ttc + 5 * ep + 2 * c) / 12


def route_progress(path: Path, xy: np.ndarray, tolerance: float = ROUTE_TOLERANCE) -> float:
    """Arc length (m) gained along ``path`` by positions ``xy`` [N, 2] driven in order.

    Each position is projected onto the path near the previous projection (within 5 m behind
    to the distance moved + 5 m ahead; nearest 0.2 m sample, refined along its heading); a
    position farther than ``tolerance`` from the path adds nothing (the ego left the route,
    e.g. went straight where the route turns) and keeps the previous projection.
    """
    xy = np.asarray(xy, dtype=np.float64)
    (s0,), _ = path.project(xy[:1])
    s_prev, start = float(s0), float(s0)
    for k in range(1, len(xy)):
        step = float(np.hypot(*(xy[k] - xy[k - 1])))
        win = (path.s >= s_prev - 5.0) & (path.s <= s_prev + step + 5.0)
        idx = np.flatnonzero(win)
        d = np.hypot(*(path.xy[idx] - xy[k]).T)
        j = int(idx[np.argmin(d)])
        if d.min() > tolerance:
            continue
        h = path.heading[j]
        r = xy[k] - path.xy[j]
        s_prev = float(np.clip(path.s[j] + np.cos(h) * r[0] + np.sin(h) * r[1], 0, path.length))
    return s_prev - start


def _progress(world: World, ep: Episode) -> tuple[float, float, float]:
    path = world.ego.path
    log_xy, _ = world.ego.trajectory.pose(np.arange(ep.times[0], world.duration + 1e-9, SIM_DT))
    logged = route_progress(path, log_xy)
    driven = route_progress(path, ep.states[:, :2])
    if logged < _MIN_LOGGED_PROGRESS:
        return 1.0, driven, logged
    return float(np.clip(round(driven / logged, 6), 0.0, 1.0)), driven, logged


def _ttc_steps(boxes: SceneBoxes, ep: Episode) -> int:
    taus = np.arange(1, int(round(_TTC_HORIZON / SIM_DT)) + 1) * SIM_DT
    bad = 0
    for t, (x, y, yaw, v) in zip(ep.times[1:], ep.states[1:]):
        if v <= 0.1:
            continue
        ec, _ = ego_box_at(np.array([x, y]), yaw)
        u = np.array([np.cos(yaw), np.sin(yaw)])
        c, oy = boxes.at(t)
        rel = c - ec
        ahead = rel @ u > 0
        reach = v * _TTC_HORIZON + np.hypot(*EGO_HALF) + np.hypot(*boxes.half.T) + 20.0
        idx = np.flatnonzero(ahead & (np.hypot(*rel.T) < reach))
        if not len(idx):
            continue
        vel = boxes.velocity(t)[idx]
        e_c = ec[None] + taus[:, None] * v * u[None]  # [N, 2]
        o_c = c[idx][None] + taus[:, None, None] * vel[None]  # [N, M, 2]
        hit = rects_overlap(e_c[:, None], yaw, EGO_HALF, o_c, oy[idx][None],
                            boxes.half[idx][None])  # fmt: skip
        bad += bool(hit.any())
    return bad


def _smooth(x: np.ndarray, n: int = 5) -> np.ndarray:
    if len(x) < n:
        return x
    pad = np.pad(x, n // 2, mode="edge")
    return np.convolve(pad, np.ones(n) / n, mode="valid")


def _comfort(ep: Episode) -> dict[str, int]:
    if len(ep.states) < 3:
        return {k: 0 for k in COMFORT_BOUNDS}
    v = _smooth(ep.states[:, 3])
    yaw = _smooth(np.unwrap(ep.states[:, 2]))
    acc = np.gradient(v, SIM_DT)
    rate = np.gradient(yaw, SIM_DT)
    q = {
        "lon_accel": acc,
        "lat_accel": v * rate,
        "lon_jerk": np.gradient(acc, SIM_DT),
        "yaw_rate": rate,
        "yaw_accel": np.gradient(rate, SIM_DT),
    }
    return {k: int(((q[k] < lo - 1e-9) | (q[k] > hi + 1e-9)).sum())
            for k, (lo, hi) in COMFORT_BOUNDS.items()}  # fmt: skip


def score_episode(world: World, ep: Episode, boxes: SceneBoxes | None = None) -> dict:
    """Scores and counts of one episode (module docstring: the definitions).

    Returns:
        A flat dict: scene, behaviour, planner, end, reason, collided_with, NC, DAC, EP, TTC,
        C, PDMS, at_fault_collision, collision, off_road, failed, ttc_steps, comfort_steps
        (per bound, 10 Hz steps out of bounds), progress_m, logged_progress_m, seconds (driven),
        saturated_steps, voxelise_ms and plan_ms (means per call).
    """
    boxes = boxes or SceneBoxes(world)
    collision = ep.end == "collision"
    at_fault = collision and ep.contact.at_fault
    failed = ep.end == "planner_error"
    ep_score, driven, logged = _progress(world, ep)
    ttc = _ttc_steps(boxes, ep)
    comfort = _comfort(ep)
    nc, dac = float(not at_fault), float(ep.end != "off_road")
    ttc_s, c_s = float(ttc == 0), float(sum(comfort.values()) == 0)
    return {
        "scene": ep.scene,
        "behaviour": ep.behaviour,
        "planner": ep.planner,
        "end": ep.end,
        "reason": ep.reason,
        "collided_with": ep.contact.key if ep.contact else "",
        "NC": nc,
        "DAC": dac,
        "EP": ep_score,
        "TTC": ttc_s,
        "C": c_s,
        "PDMS": 0.0 if failed else pdms(nc, dac, ep_score, ttc_s, c_s),
        "at_fault_collision": bool(at_fault),
        "collision": bool(collision),
        "off_road": ep.end == "off_road",
        "failed": bool(failed),
        "ttc_steps": ttc,
        "comfort_steps": comfort,
        "progress_m": round(driven, 3),
        "logged_progress_m": round(logged, 3),
        "seconds": round(float(ep.times[-1] - ep.times[0]), 3),
        "saturated_steps": ep.saturated,
        "voxelise_ms": float(np.mean(ep.voxelise_ms)) if ep.voxelise_ms else 0.0,
        "plan_ms": float(np.mean(ep.plan_ms)) if ep.plan_ms else 0.0,
    }


def aggregate(rows: list[dict]) -> dict:
    """Means of the scores and counts of the events over episodes (one planner's rows).

    Returns:
        ``{"episodes", "NC", "DAC", "EP", "TTC", "C", "PDMS"`` (means), ``"at_fault_collisions",
        "collisions", "off_road", "ttc_violations", "comfort_violations", "failures"`` (counts)}.
    """
    n = len(rows)
    if not n:
        raise ValueError("rows: expected at least one episode, got none")
    out = {"episodes": n}
    for k in SCORE_KEYS:
        out[k] = float(np.mean([r[k] for r in rows]))
    out["at_fault_collisions"] = sum(r["at_fault_collision"] for r in rows)
    out["collisions"] = sum(r["collision"] for r in rows)
    out["off_road"] = sum(r["off_road"] for r in rows)
    out["ttc_violations"] = sum(r["TTC"] == 0 for r in rows)
    out["comfort_violations"] = sum(r["C"] == 0 for r in rows)
    out["failures"] = sum(r["failed"] for r in rows)
    return out
