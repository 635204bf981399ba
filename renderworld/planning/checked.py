"""The forecast-checked plan: the learned plan, or the best candidate around it.

``Planner.plan(request, check=True)`` (and ``PlannerSession.plan(..., check=True)``) runs, after
the world model's own plan:

1. **Forecast scene** (:func:`renderworld.planning.scene.forecast_scene`): the movers of the
   current frame tracked through the history and moved by the model's mover forecast, the
   static scenery and the drivable cells, in the current ego frame;
2. **Candidates** (:func:`renderworld.planning.candidates.make_candidates`) around the plan
   and, with ``CheckConfig.steady_path``, IDM runs and brakes along the ego's steady path
   (:func:`steady_path_plan`), each starting with the ego's lateral acceleration now
   (:func:`continue_lateral_accel`);
3. **Scores** (:func:`renderworld.planning.check.score_candidates`): each candidate tracked by
   the kinematic model and scored against the forecast scene.

It reads what the request carries and nothing else: the history occupancy, the history poses
(displacements and yaws) and the model's plan (which read the command). The ego's recent motion
(speed now, the last second at 10 Hz, for comfort) comes from splines through the history poses
(:func:`past_states`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from renderworld.constants import KEYFRAME_DT, GridSpec
from renderworld.planning.candidates import Candidates, CheckConfig, make_candidates
from renderworld.planning.check import CandidateScores, score_candidates
from renderworld.planning.hold import unhold_if_safe
from renderworld.planning.kinematics import KinematicLimits
from renderworld.planning.scene import (
    MoverForecaster,
    constant_velocity_displacements,
    forecast_scene,
)
from renderworld.world.pose_retime import (
    last_step_speed,
    leader_stop_room,
    retime_along_path,
    stop_profile,
)

__all__ = [
    "CheckedPlan",
    "blend_with_previous",
    "cap_behind_leader",
    "check_plan",
    "continue_lateral_accel",
    "current_speed",
    "lateral_accel_now",
    "past_states",
    "steady_path_plan",
]


@dataclass
class CheckedPlan:
    """A checked plan.

    Attributes:
        trajectory: [S, 2] float32 metres, the chosen candidate's waypoints.
        yaws: [S] float32 radians, its headings.
        candidates: every candidate and its scores.
        timings: milliseconds: ``scene`` (tracking and moving the movers), ``candidates``,
            ``scoring``, ``check`` (their sum).
    """

    trajectory: np.ndarray
    yaws: np.ndarray
    candidates: CandidateScores
    timings: dict


def past_states(history_poses: np.ndarray, dt: float = KEYFRAME_DT, seconds: float = 1.0):
    """The ego's recent 10 Hz states from its history poses (current ego frame).

    Positions and headings are interpolated by cubic splines through the history poses (one per
    ``dt``); speeds are the spline's velocity norm.

    Args:
        history_poses: [H >= 2, 3] (x, y, yaw), oldest first, the last the current frame.
        dt: seconds between history frames.
        seconds: how far back, at most the history's span.

    Returns:
        [n, 4] (x, y, yaw, speed) at -seconds ... 0 s every 0.1 s (the last: now).
    """
    from scipy.interpolate import CubicSpline

    p = np.asarray(history_poses, dtype=np.float64)
    t = (np.arange(len(p)) - (len(p) - 1)) * dt
    span = min(seconds, -t[0])
    ts = np.round(np.arange(-span, 1e-9, 0.1), 9)
    yaw = np.unwrap(p[:, 2])
    if len(p) == 2:  # a line: constant velocity
        v = (p[1, :2] - p[0, :2]) / dt
        xy = p[1, :2] + ts[:, None] * v
        return np.column_stack([xy, np.interp(ts, t, yaw), np.full(len(ts), np.hypot(*v))])
    sx, sy, syaw = CubicSpline(t, p[:, 0]), CubicSpline(t, p[:, 1]), CubicSpline(t, yaw)
    speed = np.hypot(sx(ts, 1), sy(ts, 1))
    return np.column_stack([sx(ts), sy(ts), syaw(ts), speed])


def blend_with_previous(plan: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """[S, 3] the plan's positions blended with the previous trajectory's, step k of S weighing
    the plan k / S (the near steps follow the previous trajectory, the far ones the new plan);
    headings from the blended path's direction (the plan's where it does not move).

    Args:
        plan: [S, 3] (x, y, yaw), current ego frame.
        previous: [S, 2] positions at the same times, current ego frame.
    """
    s = len(plan)
    w = (np.arange(1, s + 1) / s)[:, None]
    xy = w * plan[:, :2] + (1 - w) * np.asarray(previous, dtype=np.float64)
    d = np.diff(np.concatenate([np.zeros((1, 2)), xy]), axis=0)
    moving = np.hypot(d[:, 0], d[:, 1]) > 0.05
    yaw = np.where(moving, np.arctan2(d[:, 1], d[:, 0]), plan[:, 2])
    return np.column_stack([xy, yaw])


def lateral_accel_now(history_poses: np.ndarray, speed_before: float, dt: float = KEYFRAME_DT):
    """The ego's lateral acceleration now (m/s^2, left +), at the end of the cubic Hermite curve
    from the previous history pose (heading and speed ``speed_before`` there) to the current one.

    That curve is the one the kinematic model tracks between two plans
    (:func:`renderworld.planning.tracking.reference_batch`); its lateral acceleration at the end
    does not depend on the end speed.

    Args:
        history_poses: [H >= 2, 3] (x, y, yaw), the last the current frame (zeros).
        speed_before: m/s at the previous history pose.
        dt: seconds between history poses.
    """
    _, y0, yaw0 = np.asarray(history_poses, dtype=np.float64)[-2]
    return float((6.0 * y0 + 2.0 * dt * speed_before * np.sin(yaw0)) / dt**2)


def continue_lateral_accel(
    waypoints: np.ndarray, accel: float, dt: float = KEYFRAME_DT, ease: bool = False
):
    """[N, S, 2] the waypoints with each first one moved sideways so that the tracked curve
    starts with lateral acceleration ``accel`` (m/s^2): the heading rate then goes on smoothly
    from the last plan's instead of jumping at the change of plan (a jump of ``w`` rad/s reads
    as about ``4.3 w`` rad/s^2 of yaw acceleration in NAVSIM's 5-state filter).

    The first segment of the tracked curve (:func:`renderworld.planning.tracking.reference_batch`)
    starts along x with lateral acceleration ``(6 y1 - y2) / dt^2`` and ends with
    ``(2 y2 - 6 y1) / dt^2``: the two add up to ``y2 / dt^2`` whatever ``y1`` is. Moving only
    ``y1`` (``ease`` False) the segment ends at ``y2 / dt^2 - accel``, where the next plan starts:
    a start off the plan's own by ``e`` ends off by ``-e``, and the car weaves at two plans' period
    without damping. With ``ease`` the second waypoint moves as well, so that the segment goes
    from ``accel`` to the plan's own lateral acceleration, its mean over the first two waypoints
    (``2 y2 / (2 dt)^2``: a centimetre's jitter of the learned waypoints moves it little).
    Plans of one waypoint are returned unchanged.

    Args:
        waypoints: [N, S, 2] metres at +dt ... +S dt, current ego frame.
        accel: m/s^2, left +.
        dt: seconds between waypoints.
        ease: also move the second waypoint (above).
    """
    wp = np.array(waypoints, dtype=np.float64)
    if wp.shape[1] >= 2:
        if ease:
            own = wp[:, 1, 1] / (2.0 * dt**2)  # [N] its mean over the first two waypoints
            wp[:, 1, 1] = (accel + own) * dt**2
        wp[:, 0, 1] = (dt**2 * accel + wp[:, 1, 1]) / 6.0
    return wp


def steady_path_plan(plan: np.ndarray, past: np.ndarray, dt: float = KEYFRAME_DT) -> np.ndarray:
    """[S, 3] (x, y, yaw) waypoints at the plan's top speed along the ego's steady path: its
    heading now, turning at its current curvature (yaw rate / speed over the last 0.2 s;
    straight below 2 m/s, where the heading rate is noise; at most 0.05 /m).

    A fallback path that needs no learned plan: where the plan turns towards an obstacle or
    sideways at a crawl, the car can still go on along the way it is heading.

    Args:
        plan: [S, >= 2] the learned plan's positions, metres, current ego frame.
        past: [n, 4] the ego's recent 10 Hz states (x, y, yaw, speed), the last one now
            (:func:`past_states`).
        dt: seconds between waypoints.
    """
    step = np.hypot(*np.diff(np.concatenate([np.zeros((1, 2)), plan[:, :2]]), axis=0).T)
    top = float(step.max()) if len(step) else 0.0
    v = float(past[-1, 3])
    kappa = 0.0
    if v > 2.0 and len(past) >= 3:
        kappa = float(np.clip((past[-1, 2] - past[-3, 2]) / 0.2 / v, -0.05, 0.05))
    s = top * np.arange(1, len(plan) + 1)
    yaw = kappa * s
    if abs(kappa) < 1e-9:
        xy = np.column_stack([s, np.zeros_like(s)])
    else:
        xy = np.column_stack([np.sin(yaw) / kappa, (1 - np.cos(yaw)) / kappa])
    return np.column_stack([xy, yaw])


def _with_steady_path(cands, plan, past, speed, scene, cfg, dt, cruise_speed):
    """``cands`` and, after them, the IDM runs and brakes along :func:`steady_path_plan`."""
    steady = steady_path_plan(plan, past, dt)
    extra = make_candidates(steady[:, :2], steady[:, 2], speed, scene,
                            replace(cfg, offsets_m=(0.0,), pass_parked=False), dt,
                            cruise_speed)  # fmt: skip
    keep = np.array([k != "plan" for k in extra.kind])
    return Candidates(
        np.concatenate([cands.waypoints, extra.waypoints[keep]]),
        list(cands.kind) + [f"steady_{k}" for k, m in zip(extra.kind, keep) if m],
        np.concatenate([cands.offset_m, extra.offset_m[keep]]),
        np.concatenate([cands.speed, extra.speed[keep]]),
        cands.reference_m,
        cands.path,
    )


def cap_behind_leader(
    waypoints: np.ndarray, tracks: list, history_poses: np.ndarray, grid: GridSpec, dt: float
) -> np.ndarray:
    """[N, S, 2] the candidates' waypoints, each retimed along its own path
    (:func:`~renderworld.world.pose_retime.retime_along_path`) to stay within the stop behind a
    leader coming to a stop (:func:`~renderworld.world.pose_retime.leader_stop_room`,
    :func:`~renderworld.world.pose_retime.stop_profile` from the ego's speed now); unchanged,
    bit for bit, where there is no such leader or a candidate stays short of it."""
    room = leader_stop_room(tracks, history_poses, grid)
    if room is None:
        return waypoints
    v0 = last_step_speed(history_poses, dt)
    s = np.cumsum(np.linalg.norm(np.diff(waypoints, axis=1, prepend=0.0), axis=-1), axis=-1)
    capped = np.stack([stop_profile(si, v0, room, dt) for si in s])
    past = (capped < s - 1e-9).any(axis=-1)
    if not past.any():
        return waypoints
    poses = np.concatenate([waypoints[past], np.zeros((*waypoints[past].shape[:-1], 1))], -1)
    f = np.where(s[past] > 1e-6, capped[past] / np.maximum(s[past], 1e-6), 1.0)
    out = waypoints.copy()
    out[past] = retime_along_path(torch.from_numpy(poses), torch.from_numpy(f))[..., :2].numpy()
    return out


def current_speed(history_poses: np.ndarray, dt: float = KEYFRAME_DT) -> float:
    """The ego's speed now (m/s): :func:`past_states`' last speed."""
    return float(past_states(history_poses, dt, seconds=0.0)[-1, 3])


def check_plan(
    history_occupancy: np.ndarray,
    history_poses: np.ndarray,
    plan_poses: np.ndarray,
    grid: GridSpec,
    config: CheckConfig | None = None,
    limits: KinematicLimits | None = None,
    movers: MoverForecaster = constant_velocity_displacements,
    dt: float = KEYFRAME_DT,
    cruise_speed: float | None = None,
    previous: np.ndarray | None = None,
) -> CheckedPlan:
    """Check a learned plan against the forecast (module docstring).

    Args:
        history_occupancy: [H, X, Y, Z] uint8 Occ3D labels, each frame in its own ego frame.
        history_poses: [H, 3] (x, y, yaw) of those frames in the current ego frame.
        plan_poses: [S, 3] (x, y, yaw) the learned plan, current ego frame.
        grid: the occupancy grid.
        config: the checker's knobs (default :class:`CheckConfig`).
        limits: the kinematic model's limits.
        movers: the mover forecast (default: each tracked mover at its fitted velocity).
        dt: seconds between frames and waypoints.
        cruise_speed: the speed the ego drove at recently, m/s (None: the fastest history
            step's); a much slower plan while the ego stands is stalled
            (:class:`~renderworld.planning.candidates.CheckConfig`).
            previous: [S, 2] the trajectory chosen one step before, carried on to now in the
                current ego frame (:class:`renderworld.planning.PlannerSession` keeps it) or
                None: the candidates' path then starts on it and ends on the new plan
                (:func:`blend_with_previous`), so consecutive plans agree where the car is
                about to drive.

    Raises:
        ValueError: naming the argument on a shape mismatch.
    """
    cfg = config or CheckConfig()
    plan = np.asarray(plan_poses, dtype=np.float64)
    if plan.ndim != 2 or plan.shape[1] != 3 or len(plan) < 1:
        raise ValueError(f"plan_poses: expected [S >= 1, 3] (x, y, yaw), got {plan.shape}")
    hist = np.asarray(history_poses, dtype=np.float64)
    if hist.ndim != 2 or hist.shape[1] != 3 or len(hist) < 2:
        raise ValueError(f"history_poses: expected [H >= 2, 3] (x, y, yaw), got {hist.shape}")
    if previous is not None:
        plan = blend_with_previous(plan, previous)
    t0 = time.perf_counter()
    scene = forecast_scene(history_occupancy, hist, grid, len(plan), dt, movers)
    t1 = time.perf_counter()
    past = past_states(hist, dt)
    speed = float(past[-1, 3])
    if cruise_speed is None:
        cruise_speed = float(np.hypot(*np.diff(hist[:, :2], axis=0).T).max() / dt)
    cands = make_candidates(plan[:, :2], plan[:, 2], speed, scene, cfg, dt, cruise_speed)
    if cfg.steady_path:
        cands = _with_steady_path(cands, plan, past, speed, scene, cfg, dt, cruise_speed)
    accel = None
    if cfg.continuous_start and speed > cfg.continuous_min_speed:
        step = int(round(dt / 0.1))
        accel = lateral_accel_now(hist, float(past[-1 - step, 3]), dt) if len(past) > step else 0.0

    def start(wp):  # every candidate's start and the leader-stop cap
        if accel is not None:
            wp = continue_lateral_accel(wp, accel, dt, cfg.continuous_ease)
        if cfg.leader_stop_cap:
            wp = cap_behind_leader(wp, scene.tracks, hist, grid, dt)
        return wp

    cands.waypoints = start(cands.waypoints)
    if cfg.hold_if_unsafe:
        unhold_if_safe(cands, plan, speed, past, scene, cfg, start, limits, dt, previous)
    t2 = time.perf_counter()
    scores = score_candidates(cands, scene, past, cfg, limits, dt, previous)
    t3 = time.perf_counter()
    b = scores.best
    traj = scores.waypoints[b]
    if np.array_equal(traj, plan[:, :2]):  # the learned plan itself
        yaws = plan[:, 2]
    else:  # the kinematic model's headings at the waypoints
        step = int(round(dt / 0.1))
        yaws = scores.states[b, step - 1 :: step, 2][: len(plan)]
    ms = {"scene": 1e3 * (t1 - t0), "candidates": 1e3 * (t2 - t1), "scoring": 1e3 * (t3 - t2)}
    ms["check"] = sum(ms.values())
    return CheckedPlan(traj.astype(np.float32), yaws.astype(np.float32), scores, ms)
