"""The ego's kinematic model: a plan (6 waypoints at 0.5 s) tracked at 10 Hz.

The ego is a unicycle with state (x, y, yaw, speed) in the scene frame (metres, radians, m/s;
the rear axle, as every ego pose of the package). Between two plans (one keyframe, 0.5 s) it is
advanced in :data:`SIM_DT` steps toward a reference: a cubic Hermite curve in time through the
current position (with the current velocity) and the plan's waypoints (velocities by central
differences, at the last waypoint along the arc through the last three, capped as in
Fritsch-Carlson's monotone cubic so that it never overshoots a stop),
so a plan the car can drive is driven as planned. With ``spline=True`` the tangents at the
waypoints are instead those of the C2 cubic spline (the current velocity at the start, zero
acceleration at the end): the acceleration, hence the heading rate, does not jump at a waypoint
(the forecast-checked planner judges its candidates' comfort on it). Each step:

* the reference pose at the next step (position, heading along the curve) is taken as is when
  reaching it is **feasible**: speed <= ``max_speed``, longitudinal acceleration within
  [-``max_decel``, ``max_accel``], yaw rate within ``max_yaw_rate``, ``max_lat_accel`` / v and
  ``max_curvature`` x v, no reversing and no sideways slip (the step's lateral component
  against its mean heading <= 2 cm + 2 % of the step);
* otherwise the controls saturate: the ego steers toward the reference point (yaw rate clipped)
  (or keeps its heading when the point is behind it) and takes the speed that closes the gap
  along its heading (acceleration clipped, never reversing), then moves along its heading.

The limits are physical (what the car can do), not comfort bounds: comfort is scored afterwards
(:mod:`renderworld.sim.closed_loop.scores`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import KEYFRAME_DT

__all__ = [
    "SIM_DT",
    "STEPS_PER_KEYFRAME",
    "KinematicLimits",
    "EgoState",
    "hermite_tangents",
    "track_plan",
]

#: Simulation step, seconds (10 Hz): tracking, collisions and scores run at this rate.
SIM_DT = 0.1
STEPS_PER_KEYFRAME = int(round(KEYFRAME_DT / SIM_DT))


@dataclass(frozen=True)
class KinematicLimits:
    """What the simulated car can do.

    Attributes:
        max_speed: m/s.
        max_accel: m/s^2, throttle.
        max_decel: m/s^2, full braking (positive).
        max_yaw_rate: rad/s.
        max_lat_accel: m/s^2 (speed x yaw rate).
        max_curvature: 1/m, yaw rate per speed (a 4 m turning radius: no turning on the spot).
    """

    max_speed: float = 25.0
    max_accel: float = 4.0
    max_decel: float = 8.0
    max_yaw_rate: float = 1.0
    max_lat_accel: float = 6.0
    max_curvature: float = 0.25


@dataclass(frozen=True)
class EgoState:
    """Rear-axle pose and speed, scene frame: x, y (m), yaw (rad), speed (m/s, >= 0)."""

    x: float
    y: float
    yaw: float
    speed: float

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y])


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _hermite(p0, p1, v0, v1, u, h):
    """Position and derivative (per second) of the cubic Hermite segment at fraction ``u``."""
    u2, u3 = u * u, u * u * u
    pos = (
        (2 * u3 - 3 * u2 + 1) * p0
        + (u3 - 2 * u2 + u) * h * v0
        + (-2 * u3 + 3 * u2) * p1
        + (u3 - u2) * h * v1
    )
    der = (
        (6 * u2 - 6 * u) * p0
        + (3 * u2 - 4 * u + 1) * h * v0
        + (-6 * u2 + 6 * u) * p1
        + (3 * u2 - 2 * u) * h * v1
    ) / h
    return pos, der


def _arc_end_tangent(pts: np.ndarray, h: float) -> np.ndarray:
    """[..., 2] m/s: the last chord's speed along the heading a circular arc through the last
    three knots [..., M, 2] has at the end (the chord's own direction where M < 3, a chord is
    under 1 cm or the path folds back): a turn goes on turning to the end of the curve instead
    of straightening in its last segment and swinging the heading back."""
    last = pts[..., -1, :] - pts[..., -2, :]
    if pts.shape[-2] < 3:
        return last / h
    prev = pts[..., -2, :] - pts[..., -3, :]
    l1, l2 = np.hypot(prev[..., 0], prev[..., 1]), np.hypot(last[..., 0], last[..., 1])
    a2 = np.arctan2(last[..., 1], last[..., 0])
    turn = _wrap(a2 - np.arctan2(prev[..., 1], prev[..., 0]))
    arc = (l1 > 0.01) & (l2 > 0.01) & (np.abs(turn) < np.pi / 2)
    end = a2 + np.where(arc, turn * l2 / np.maximum(l1 + l2, 1e-9), 0.0)
    return (l2 / h)[..., None] * np.stack([np.cos(end), np.sin(end)], -1)


def hermite_tangents(pts: np.ndarray, v0: np.ndarray, h: float, spline: bool) -> np.ndarray:
    """Velocities at the knots of the tracked reference curve (module docstring).

    Catmull-Rom (central differences; at the end the arc through the last three knots:
    :func:`_arc_end_tangent`), or with ``spline`` the C2 cubic
    spline's (tridiagonal solve by the Thomas algorithm: elementwise, so one plan and a batch
    give the same bits), then capped as Fritsch-Carlson's monotone cubic.

    Args:
        pts: [..., M >= 2, 2] the current position and the waypoints, metres.
        v0: [..., 2] the current velocity, m/s.
        h: seconds between knots.
        spline: C2 spline tangents instead of Catmull-Rom's.

    Returns:
        [..., M, 2] m/s.
    """
    m = pts.shape[-2]
    vel = np.empty_like(pts)
    vel[..., 0, :] = v0
    if spline:  # v[i-1] + 4 v[i] + v[i+1] = 3 (p[i+1] - p[i-1]) / h; v[M-2] + 2 v[M-1] = ...
        diag = np.full(m, 4.0)
        diag[-1] = 2.0
        rhs = np.empty_like(pts)
        rhs[..., 1:-1, :] = 3.0 * (pts[..., 2:, :] - pts[..., :-2, :]) / h
        rhs[..., -1, :] = 3.0 * (pts[..., -1, :] - pts[..., -2, :]) / h
        rhs[..., 1, :] -= v0
        upper = np.zeros(m)
        upper[1] = 1.0 / diag[1]
        rhs[..., 1, :] /= diag[1]
        for i in range(2, m):
            den = diag[i] - upper[i - 1]
            upper[i] = 1.0 / den
            rhs[..., i, :] = (rhs[..., i, :] - rhs[..., i - 1, :]) / den
        vel[..., -1, :] = rhs[..., -1, :]
        for i in range(m - 2, 0, -1):
            vel[..., i, :] = rhs[..., i, :] - upper[i] * vel[..., i + 1, :]
    else:
        vel[..., 1:-1, :] = (pts[..., 2:, :] - pts[..., :-2, :]) / (2 * h)
        vel[..., -1, :] = _arc_end_tangent(pts, h)
    # Fritsch-Carlson: a tangent at most 3x the shorter neighbouring segment's speed, so the
    # curve never overshoots a waypoint where the plan slows down or stops.
    seg = np.hypot(pts[..., 1:, 0] - pts[..., :-1, 0], pts[..., 1:, 1] - pts[..., :-1, 1]) / h
    inf = np.full(seg.shape[:-1] + (1,), np.inf)
    cap = 3.0 * np.minimum(np.concatenate([inf, seg], -1), np.concatenate([seg, inf], -1))
    norm = np.hypot(vel[..., 0], vel[..., 1])
    vel *= np.where(norm > cap, cap / np.maximum(norm, 1e-12), 1.0)[..., None]
    return vel


def reference(
    state: EgoState, waypoints: np.ndarray, steps: int, spline: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The tracked reference at the next ``steps`` simulation steps.

    Args:
        state: the current ego state.
        waypoints: [S, 2] scene-frame positions at +0.5 ... +S/2 s.
        steps: how many :data:`SIM_DT` steps (at most ``S`` keyframes' worth).
        spline: C2 spline tangents (module docstring) instead of Catmull-Rom's.

    Returns:
        (positions [steps, 2], headings [steps]) in the scene frame; a heading where the
        reference stands still is the current yaw.
    """
    pts = np.concatenate([state.xy[None], np.asarray(waypoints, dtype=np.float64)])
    h = KEYFRAME_DT
    v0 = state.speed * np.array([np.cos(state.yaw), np.sin(state.yaw)])
    vel = hermite_tangents(pts[None], v0[None], h, spline)[0]
    out_p = np.empty((steps, 2))
    out_h = np.empty(steps)
    heading = state.yaw
    for i in range(steps):
        t = (i + 1) * SIM_DT
        k = min(int(np.floor(t / h - 1e-9)), len(pts) - 2)
        u = (t - k * h) / h
        p, d = _hermite(pts[k], pts[k + 1], vel[k], vel[k + 1], u, h)
        if np.hypot(*d) > 0.05:
            heading = float(np.arctan2(d[1], d[0]))
        out_p[i], out_h[i] = p, heading
    return out_p, out_h


def _feasible(state: EgoState, p: np.ndarray, yaw: float, lim: KinematicLimits) -> bool:
    step = p - state.xy
    dist = float(np.hypot(*step))
    speed = dist / SIM_DT
    dyaw = float(_wrap(yaw - state.yaw))
    mid = state.yaw + dyaw / 2
    lateral = abs(-np.sin(mid) * step[0] + np.cos(mid) * step[1])
    forward = np.cos(mid) * step[0] + np.sin(mid) * step[1]
    rate = abs(dyaw) / SIM_DT
    acc = (speed - state.speed) / SIM_DT
    return bool(
        speed <= lim.max_speed
        and -lim.max_decel - 1e-9 <= acc <= lim.max_accel + 1e-9
        and rate <= lim.max_yaw_rate + 1e-9
        and rate * max(speed, state.speed) <= lim.max_lat_accel + 1e-9
        and rate <= lim.max_curvature * max(speed, state.speed) + 1e-9
        and lateral <= 0.02 + 0.02 * dist
        and forward >= -1e-9
    )


def _saturate(state: EgoState, p: np.ndarray, yaw: float, lim: KinematicLimits) -> EgoState:
    step = p - state.xy
    dist = float(np.hypot(*step))
    target = float(np.arctan2(step[1], step[0])) if dist > 0.05 else yaw
    if abs(_wrap(target - state.yaw)) > np.pi / 2:  # a point behind: no reversing, keep heading
        target = yaw
    v_max_turn = lim.max_lat_accel / max(state.speed, 1e-6)
    rate_lim = min(lim.max_yaw_rate, v_max_turn, lim.max_curvature * state.speed)
    rate = float(np.clip(_wrap(target - state.yaw) / SIM_DT, -rate_lim, rate_lim))
    new_yaw = state.yaw + rate * SIM_DT
    mid = state.yaw + rate * SIM_DT / 2
    along = np.cos(mid) * step[0] + np.sin(mid) * step[1]
    v_goal = max(along, 0.0) / SIM_DT
    lo = max(state.speed - lim.max_decel * SIM_DT, 0.0)
    hi = min(state.speed + lim.max_accel * SIM_DT, lim.max_speed)
    v = float(np.clip(v_goal, lo, hi))
    x = state.x + v * SIM_DT * np.cos(mid)
    y = state.y + v * SIM_DT * np.sin(mid)
    return EgoState(float(x), float(y), float(new_yaw), v)


def track_plan(
    state: EgoState,
    waypoints: np.ndarray,
    limits: KinematicLimits,
    steps: int,
    spline: bool = False,
) -> tuple[list[EgoState], int]:
    """Advance the ego ``steps`` simulation steps along a plan.

    Args:
        state: the ego state when the plan was made.
        waypoints: [S, 2] scene-frame positions at +0.5 ... +S/2 s (finite).
        limits: the car's limits.
        steps: simulation steps to run (e.g. :data:`STEPS_PER_KEYFRAME`).
        spline: track the C2 spline through the waypoints (module docstring).

    Returns:
        (the states after each step [steps], how many steps saturated a limit).
    """
    ref_p, ref_h = reference(state, waypoints, steps, spline)
    out, saturated = [], 0
    for p, yaw in zip(ref_p, ref_h):
        if _feasible(state, p, float(yaw), limits):
            speed = float(np.hypot(*(p - state.xy)) / SIM_DT)
            state = EgoState(float(p[0]), float(p[1]), float(state.yaw + _wrap(yaw - state.yaw)),
                             speed)  # fmt: skip
        else:
            state = _saturate(state, p, float(yaw), limits)
            saturated += 1
        out.append(state)
    return out, saturated
