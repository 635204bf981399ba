"""Many plans tracked at once by the package's kinematic model (numpy, vectorised).

:func:`track_plans` advances N ego states along N plans exactly as
:func:`renderworld.planning.kinematics.track_plan` advances one (the same reference curve, the
same feasibility test, the same saturated controls), with every step computed for all N plans
in one array operation: the forecast-checked planner tracks its candidates with it.
:func:`~renderworld.planning.kinematics.track_plan` is its reference twin and the tests' oracle.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import KEYFRAME_DT
from renderworld.planning.kinematics import SIM_DT, KinematicLimits, hermite_tangents

__all__ = ["reference_batch", "track_plans"]


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def reference_batch(
    states: np.ndarray, waypoints: np.ndarray, steps: int, spline: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The reference curves of N plans (:func:`renderworld.planning.kinematics.reference`).

    Args:
        states: [N, 4] (x, y, yaw, speed): metres, radians, m/s, one frame for all.
        waypoints: [N, S, 2] positions at +0.5 ... +S/2 s in that frame.
        steps: simulation steps (:data:`SIM_DT` each), at most ``S`` keyframes' worth.
        spline: C2 spline tangents instead of Catmull-Rom's
            (:func:`~renderworld.planning.kinematics.hermite_tangents`).

    Returns:
        (positions [N, steps, 2], headings [N, steps]).
    """
    st = np.asarray(states, dtype=np.float64)
    pts = np.concatenate([st[:, None, :2], np.asarray(waypoints, dtype=np.float64)], axis=1)
    n, m = pts.shape[:2]
    h = KEYFRAME_DT
    v0 = st[:, 3:4] * np.stack([np.cos(st[:, 2]), np.sin(st[:, 2])], -1)
    vel = hermite_tangents(pts, v0, h, spline)
    out_p = np.empty((n, steps, 2))
    out_h = np.empty((n, steps))
    heading = st[:, 2].copy()
    for i in range(steps):
        t = (i + 1) * SIM_DT
        k = min(int(np.floor(t / h - 1e-9)), m - 2)
        u = (t - k * h) / h
        u2, u3 = u * u, u * u * u
        p0, p1, v0, v1 = pts[:, k], pts[:, k + 1], vel[:, k], vel[:, k + 1]
        p = (2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * h * v0
        p = p + (-2 * u3 + 3 * u2) * p1 + (u3 - u2) * h * v1
        d = (6 * u2 - 6 * u) * p0 + (3 * u2 - 4 * u + 1) * h * v0
        d = (d + (-6 * u2 + 6 * u) * p1 + (3 * u2 - 2 * u) * h * v1) / h
        moving = np.hypot(d[:, 0], d[:, 1]) > 0.05
        heading = np.where(moving, np.arctan2(d[:, 1], d[:, 0]), heading)
        out_p[:, i], out_h[:, i] = p, heading
    return out_p, out_h


def track_plans(
    states: np.ndarray,
    waypoints: np.ndarray,
    limits: KinematicLimits,
    steps: int,
    spline: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Advance N ego states ``steps`` simulation steps along N plans.

    Args:
        states: [N, 4] (x, y, yaw, speed) when the plans were made (metres, radians, m/s; speed
            >= 0), one frame for all (e.g. the current ego frame: zeros and the speed).
        waypoints: [N, S, 2] finite positions at +0.5 ... +S/2 s in the same frame.
        limits: the car's limits.
        steps: simulation steps to run.
        spline: track the C2 spline through the waypoints (as ``track_plan``'s ``spline``).

    Returns:
        (states after each step [N, steps, 4], steps that saturated a limit [N] int).

    Raises:
        ValueError: naming ``states`` / ``waypoints`` on a shape mismatch.
    """
    st = np.asarray(states, dtype=np.float64)
    wp = np.asarray(waypoints, dtype=np.float64)
    if st.ndim != 2 or st.shape[1] != 4:
        raise ValueError(f"states: expected [N, 4] (x, y, yaw, speed), got {st.shape}")
    if wp.ndim != 3 or wp.shape[0] != st.shape[0] or wp.shape[2] != 2 or wp.shape[1] < 1:
        raise ValueError(f"waypoints: expected [{st.shape[0]}, S >= 1, 2], got {wp.shape}")
    ref_p, ref_h = reference_batch(st, wp, steps, spline)
    lim = limits
    x, y, yaw, v = (st[:, i].copy() for i in range(4))
    out = np.empty((st.shape[0], steps, 4))
    saturated = np.zeros(st.shape[0], dtype=np.int64)
    for i in range(steps):
        p, ref_yaw = ref_p[:, i], ref_h[:, i]
        sx, sy = p[:, 0] - x, p[:, 1] - y
        dist = np.hypot(sx, sy)
        speed = dist / SIM_DT
        dyaw = _wrap(ref_yaw - yaw)
        mid = yaw + dyaw / 2
        lateral = np.abs(-np.sin(mid) * sx + np.cos(mid) * sy)
        forward = np.cos(mid) * sx + np.sin(mid) * sy
        rate = np.abs(dyaw) / SIM_DT
        acc = (speed - v) / SIM_DT
        top = np.maximum(speed, v)
        ok = (
            (speed <= lim.max_speed)
            & (acc >= -lim.max_decel - 1e-9)
            & (acc <= lim.max_accel + 1e-9)
            & (rate <= lim.max_yaw_rate + 1e-9)
            & (rate * top <= lim.max_lat_accel + 1e-9)
            & (rate <= lim.max_curvature * top + 1e-9)
            & (lateral <= 0.02 + 0.02 * dist)
            & (forward >= -1e-9)
        )
        # Saturated controls (kinematics._saturate), computed for all and used where not ok.
        target = np.where(dist > 0.05, np.arctan2(sy, sx), ref_yaw)
        target = np.where(np.abs(_wrap(target - yaw)) > np.pi / 2, ref_yaw, target)
        rate_lim = np.minimum(
            np.minimum(lim.max_yaw_rate, lim.max_lat_accel / np.maximum(v, 1e-6)),
            lim.max_curvature * v,
        )
        s_rate = np.clip(_wrap(target - yaw) / SIM_DT, -rate_lim, rate_lim)
        s_mid = yaw + s_rate * SIM_DT / 2
        along = np.cos(s_mid) * sx + np.sin(s_mid) * sy
        v_goal = np.maximum(along, 0.0) / SIM_DT
        lo = np.maximum(v - lim.max_decel * SIM_DT, 0.0)
        hi = np.minimum(v + lim.max_accel * SIM_DT, lim.max_speed)
        s_v = np.clip(v_goal, lo, hi)
        x = np.where(ok, p[:, 0], x + s_v * SIM_DT * np.cos(s_mid))
        y = np.where(ok, p[:, 1], y + s_v * SIM_DT * np.sin(s_mid))
        yaw = np.where(ok, yaw + _wrap(ref_yaw - yaw), yaw + s_rate * SIM_DT)
        v = np.where(ok, speed, s_v)
        saturated += ~ok
        out[:, i] = np.stack([x, y, yaw, v], -1)
    return out, saturated
