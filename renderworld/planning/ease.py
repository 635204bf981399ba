"""The learned plan's hold-back with its braking spread evenly over the horizon.

IDM holds the learned plan back behind a leader (:mod:`renderworld.planning.idm`) by braking
hardest at once and easing off later: its acceleration answers the gap and the closing speed of
now. The car re-plans every 0.5 s and drives only the first half second of each plan, so it
drives that hardest start again and again, and a stop that a steady 3 m/s^2 would have made
comfortably breaks NAVSIM's -4.05 m/s^2 bound. With ``CheckConfig.ease_hold_decel`` the held-back
plan instead brakes at the one constant deceleration that ends the horizon where IDM's does
(no farther along the path), as long as that deceleration is at most the knob; a harder stop
keeps IDM's profile. Only behind a road user driving ahead in the corridor now (a lead car that
brakes, a car that has cut in) is it eased: one that stands, or crosses or enters the path,
gives no room as it moves, and there IDM's early braking stays. The ease is ahead of IDM's
profile in between: the check's collision and time-to-collision scores against the forecast
judge it like any candidate. Off by default (docs/planner.md).
"""

from __future__ import annotations

import numpy as np

from renderworld.planning.idm import FRONT, Leaders

__all__ = ["MIN_LEAD_SPEED", "ease_hold", "leaders_move_on"]

#: m/s: the least speed along the path of a leader the hold-back is eased behind.
MIN_LEAD_SPEED = 3.0


def leaders_move_on(lead: Leaders, s_held: np.ndarray, v0: float, dt: float) -> bool:
    """Whether the hold-back is behind a road user driving ahead in the corridor: the leader of
    now is in it and moves along the path at :data:`MIN_LEAD_SPEED` or more (it may brake to a
    stop later), and no leader the held-back plan has at a waypoint is only about to enter it
    (a crossing or oncoming road user gives no room as it moves).

    Args:
        lead: the forecast leaders along the plan's path (rows every ``lead.sub_dt`` s).
        s_held: [S] the held-back plan's arc lengths at +dt ... +S dt, metres.
        v0: the ego's speed now, m/s.
        dt: seconds between waypoints.
    """
    if not lead.arc[0].size:
        return False
    gap, j = lead.nearest_index(0, np.array([FRONT]), v0)
    if not np.isfinite(gap[0]) or lead.speed[0][j[0]] < MIN_LEAD_SPEED:
        return False
    if lead.delay is not None and lead.delay[0][j[0]] > 0:
        return False
    step = int(round(dt / lead.sub_dt))
    for w, s in enumerate(np.asarray(s_held, dtype=np.float64)):
        row = min((w + 1) * step, len(lead.arc) - 1)
        if lead.delay is None or not lead.arc[row].size:
            continue
        gap, j = lead.nearest_index(row, np.array([s + FRONT]), v0)
        if np.isfinite(gap[0]) and lead.delay[row][j[0]] > 0:
            return False
    return True


def ease_hold(
    s_held: np.ndarray, s_plan: np.ndarray, v0: float, max_decel: float, dt: float
) -> np.ndarray:
    """[S] arc lengths (metres along the plan's path) of the eased hold-back.

    Args:
        s_held: [S] the held-back plan's arc lengths at +dt ... +S dt (IDM's cap, at most
            ``s_plan``).
        s_plan: [S] the learned plan's own arc lengths (never exceeded).
        v0: the ego's speed now, m/s.
        max_decel: the hardest constant deceleration the ease may take, m/s^2 (positive).
        dt: seconds between waypoints.

    Returns:
        ``min(s_plan, v0 t - d t^2 / 2)`` (standing once stopped) with the constant ``d`` that
        ends at ``s_held[-1]``; ``s_held`` itself where no braking is needed (``s_held[-1]``
        at least ``v0`` times the horizon, or ``v0`` <= 0) or ``d`` exceeds ``max_decel``.

    Raises:
        ValueError: naming ``s_held`` when its shape differs from ``s_plan``'s, or
            ``max_decel`` when it is not positive.
    """
    s_held = np.asarray(s_held, dtype=np.float64)
    s_plan = np.asarray(s_plan, dtype=np.float64)
    if s_held.shape != s_plan.shape or s_held.ndim != 1 or len(s_held) < 1:
        raise ValueError(f"s_held: expected [S] like s_plan {s_plan.shape}, got {s_held.shape}")
    if not max_decel > 0.0:
        raise ValueError(f"max_decel: expected a positive deceleration (m/s^2), got {max_decel}")
    t = np.arange(1, len(s_held) + 1) * dt
    horizon = t[-1]
    end = max(float(s_held[-1]), 0.0)
    if v0 <= 0.0 or end >= v0 * horizon:
        return s_held
    if end >= 0.5 * v0 * horizon:  # still moving at the horizon
        decel = 2.0 * (v0 * horizon - end) / horizon**2
    elif end > 0.0:  # stops within it, at ``end``
        decel = v0 * v0 / (2.0 * end)
    else:
        return s_held
    if decel > max_decel:
        return s_held
    tt = np.minimum(t, v0 / decel)
    return np.minimum(s_plan, v0 * tt - 0.5 * decel * tt * tt)
