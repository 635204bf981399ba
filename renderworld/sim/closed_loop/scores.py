"""Closed-loop scores of an episode, NAVSIM-style, and their aggregates per behaviour.

Per episode (0/1 unless said), from the 10 Hz states:

* ``NC`` (no at-fault collision, in {0, 0.5, 1}): 0 when the episode ended in a contact the ego
  was at fault for with an agent (``vehicle.*``, ``human.*``), 0.5 with a static object (any
  other category), 1 otherwise; contacts the ego was not at fault for cost nothing (the rules,
  NAVSIM's: :mod:`renderworld.sim.closed_loop.contacts`).
* ``DAC`` (drivable-area compliance): 0 when a corner or edge midpoint of the ego box left the
  driveable surface.
* ``EP`` (ego progress, in [0, 1]): arc length driven along the logged ego's path (the route;
  :func:`route_progress`: nothing counts while the ego is more than 4 m off it) over the
  logged ego's over the same time (start to scene end, 10 Hz), clipped to [0, 1], rounded to
  1e-6; 1 when the logged ego moves less than 5 m. NAVSIM divides by the best collision-free,
  on-road proposal's progress instead: :func:`add_best_progress` adds that reading
  (``EP_best``, ``PDMS_best``) over the episodes of a run.
* ``TTC``: 0 when at some 10 Hz state after the start, with the ego moving (speed at least
  :data:`TTC_MIN_SPEED`, 0.005 m/s, NAVSIM's), the ego box moved along its heading at its
  speed for one of :data:`TTC_DELTAS` (0, 0.3, 0.6, 0.9 s, NAVSIM's) overlaps an object's box
  at that later time (the object's scripted trajectory), and that object's centre then, seen
  from the ego's current rear axle, is ahead (within 30 degrees of the ego heading) or, while
  the ego straddles lanes (a junction included) or is off the road, not behind (within 150
  degrees). Objects of earlier contacts the ego was not at fault for are left out.
* ``C`` (comfort): 0 when a NAVSIM bound is exceeded in some 4 s window
  (:mod:`renderworld.planning.comfort`: windows, filters and bounds).
* ``PDMS = NC x DAC x (5 TTC + 5 EP + 2 C) / 12`` (NAVSIM's PDM score with the multipliers and
  weights it uses); 0 for an episode the planner failed (``planner_error``).
"""

from __future__ import annotations

import numpy as np

from renderworld.planning.comfort import COMFORT_BOUNDS, comfort_violations
from renderworld.sim.agents import Path
from renderworld.sim.closed_loop.boxes import SceneBoxes, ego_on_road
from renderworld.sim.closed_loop.contacts import (
    AHEAD_ANGLE,
    BEHIND_ANGLE,
    ego_corners,
    relative_angle,
)
from renderworld.sim.closed_loop.episode import Episode
from renderworld.sim.closed_loop.kinematics import SIM_DT
from renderworld.sim.layout import World, ego_box_at

__all__ = [
    "COMFORT_BOUNDS",
    "ROUTE_TOLERANCE",
    "SCORE_KEYS",
    "TTC_DELTAS",
    "TTC_MIN_SPEED",
    "add_best_progress",
    "aggregate",
    "pdms",
    "route_progress",
    "score_episode",
]

SCORE_KEYS = ("NC", "DAC", "EP", "TTC", "C", "PDMS")
#: Seconds the ego box is moved ahead at constant speed and heading for TTC (NAVSIM's).
TTC_DELTAS = (0.0, 0.3, 0.6, 0.9)
#: Below this speed (m/s) the ego counts as stopped and TTC does not look (NAVSIM: 5e-3).
TTC_MIN_SPEED = 5e-3
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
    """10 Hz states (after the start) with a TTC violation (module docstring: the rule)."""
    cleared = [(c.t, c.key) for c in ep.not_at_fault_contacts]
    bad = 0
    for t, (x, y, yaw, v) in zip(ep.times[1:], ep.states[1:]):
        if v < TTC_MIN_SPEED:
            continue
        ignore = {k for tc, k in cleared if tc <= t + 1e-9}
        ec, _ = ego_box_at(np.array([x, y]), yaw)
        u = np.array([np.cos(yaw), np.sin(yaw)])
        area = None  # straddling lanes or off the road: looked up once, when needed
        for d in TTC_DELTAS:
            idx = [i for i in boxes.overlapping(t + d, ec + v * d * u, yaw)
                   if boxes.keys[i] not in ignore]  # fmt: skip
            if not idx:
                continue
            ang = relative_angle(x, y, yaw, boxes.at(t + d)[0][idx])
            if (ang < AHEAD_ANGLE).any():
                break
            if area is None:
                area = boxes.lanes.straddles(ego_corners(x, y, yaw)) or not ego_on_road(
                    boxes.world, x, y, yaw
                )
            if area and (ang <= BEHIND_ANGLE).any():
                break
        else:
            continue
        bad += 1
    return bad


def score_episode(world: World, ep: Episode, boxes: SceneBoxes | None = None) -> dict:
    """Scores and counts of one episode (module docstring: the definitions).

    Returns:
        A flat dict: scene, behaviour, planner, end, reason, collided_with (the object of the
        at-fault contact that ended the episode), contact_kind (its kind), NC, DAC, EP, TTC,
        C, PDMS, at_fault_collision, collision (any contact, at fault or not), off_road,
        failed, not_at_fault_contacts (count), not_at_fault_with (their objects' keys,
        ";"-joined), ttc_steps, comfort_steps (per bound, 10 Hz states out of it in some 4 s
        window), progress_m, logged_progress_m, seconds (driven), saturated_steps,
        voxelise_ms and plan_ms (means per call).
    """
    boxes = boxes or SceneBoxes(world)
    contact = ep.contact if ep.end == "collision" else None
    at_fault = contact is not None and contact.at_fault
    failed = ep.end == "planner_error"
    ep_score, driven, logged = _progress(world, ep)
    ttc = _ttc_steps(boxes, ep)
    comfort = comfort_violations(ep.states, SIM_DT)
    nc = 1.0 if not at_fault else (0.0 if contact.agent else 0.5)
    dac = float(ep.end != "off_road")
    ttc_s, c_s = float(ttc == 0), float(sum(comfort.values()) == 0)
    others = ep.not_at_fault_contacts
    return {
        "scene": ep.scene,
        "behaviour": ep.behaviour,
        "planner": ep.planner,
        "end": ep.end,
        "reason": ep.reason,
        "collided_with": contact.key if contact else "",
        "contact_kind": contact.kind if contact else "",
        "NC": nc,
        "DAC": dac,
        "EP": ep_score,
        "TTC": ttc_s,
        "C": c_s,
        "PDMS": 0.0 if failed else pdms(nc, dac, ep_score, ttc_s, c_s),
        "at_fault_collision": bool(at_fault),
        "collision": bool(contact is not None or others),
        "off_road": ep.end == "off_road",
        "failed": bool(failed),
        "not_at_fault_contacts": len(others),
        "not_at_fault_with": ";".join(c.key for c in others),
        "ttc_steps": ttc,
        "comfort_steps": comfort,
        "progress_m": round(driven, 3),
        "logged_progress_m": round(logged, 3),
        "seconds": round(float(ep.times[-1] - ep.times[0]), 3),
        "saturated_steps": ep.saturated,
        "voxelise_ms": float(np.mean(ep.voxelise_ms)) if ep.voxelise_ms else 0.0,
        "plan_ms": float(np.mean(ep.plan_ms)) if ep.plan_ms else 0.0,
    }


def add_best_progress(rows: list[dict]) -> None:
    """Add ``EP_best`` and ``PDMS_best`` to every row of a run, in place.

    ``EP_best`` is NAVSIM's progress reading: the row's ``progress_m`` over the largest
    ``progress_m`` of the rows on the same scene (any planner, log replay included) with NC 1
    and DAC 1 (no at-fault collision, never off the road; a contact the ego was not at fault
    for does not disqualify, as NAVSIM's NC stays 1 for it) that the planner did not fail,
    clipped to [0, 1] and rounded to 1e-6; 1 when that largest progress is under 5 m or no row
    qualifies (NAVSIM: 1 below its 5 m progress threshold). ``PDMS_best`` is :func:`pdms` with
    ``EP_best`` (0 for a failed episode).

    Raises:
        ValueError: naming ``rows`` when a row lacks a key the scores give.
    """
    need = ("scene", "NC", "DAC", "TTC", "C", "failed", "progress_m")
    for r in rows:
        missing = [k for k in need if k not in r]
        if missing:
            raise ValueError(f"rows: expected score_episode rows, a row lacks {missing}")
    best: dict[str, float] = {}
    for r in rows:
        if r["NC"] == 1.0 and r["DAC"] == 1.0 and not r["failed"]:
            best[r["scene"]] = max(best.get(r["scene"], 0.0), float(r["progress_m"]))
    for r in rows:
        b = best.get(r["scene"], 0.0)
        if b < _MIN_LOGGED_PROGRESS:
            ep_best = 1.0
        else:
            ep_best = float(np.clip(round(r["progress_m"] / b, 6), 0.0, 1.0))
        r["EP_best"] = ep_best
        r["PDMS_best"] = 0.0 if r["failed"] else pdms(r["NC"], r["DAC"], ep_best, r["TTC"], r["C"])


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
