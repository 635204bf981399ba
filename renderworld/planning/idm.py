"""The Intelligent Driver Model (Treiber) along a path, behind the forecast's leaders.

PDM-Closed (nuPlan, NAVSIM) simulates its proposals with IDM behind the leading agent; here the
leaders are the forecast obstacle points inside the ego's corridor at each moment
(:func:`leaders`): a mover where the forecast puts it then, or static scenery, moving along the
path at its velocity's component, never backwards. A pedestrian who will have crossed is not
waited for; one who will be in the lane is.

Frames: the current ego frame (x forward, y left; metres, seconds, m/s); arc lengths along the
path from the ego's rear axle now.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import EGO_CENTRE_OFFSET, EGO_LENGTH, EGO_WIDTH
from renderworld.planning.scene import ForecastScene

__all__ = ["BEHIND_M", "FRONT", "Leaders", "idm_arc", "leaders", "too_close"]

FRONT = EGO_CENTRE_OFFSET + EGO_LENGTH / 2  # rear axle -> front bumper, metres
BEHIND_M = 1.0  # corridor points this far behind the front bumper still lead, metres


@dataclass
class Leaders:
    """Forecast obstacles in the ego's corridor over time, along a path.

    Attributes:
        arc: [T, Q] arc length (metres, from the ego's rear axle now) at which each obstacle
            point lies in the corridor at time ``t * sub_dt`` (inf: outside it then).
        speed: [T, Q] the point's velocity component along the path there, m/s (never < 0).
        sub_dt: seconds between rows.
    """

    arc: np.ndarray
    speed: np.ndarray
    sub_dt: float

    def nearest(self, i: int, front: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gap [F] metres, speed [F] m/s) of the leader at row ``i`` for front bumpers at arc
        ``front`` [F] (inf, 0 where none): the nearest point ahead, counting points up to
        :data:`BEHIND_M` behind the bumper (they are about to touch it)."""
        arc = self.arc[min(i, len(self.arc) - 1)]
        if not arc.size:
            return np.full(len(front), np.inf), np.zeros(len(front))
        ahead = arc[None] > front[:, None] - BEHIND_M  # [F, Q]
        gaps = np.where(ahead, arc[None] - front[:, None], np.inf)
        j = gaps.argmin(1)
        gap = gaps[np.arange(len(front)), j]
        lead_v = np.where(np.isfinite(gap), self.speed[min(i, len(self.arc) - 1)][j], 0.0)
        return gap, lead_v


def leaders(
    scene: ForecastScene, path, offsets: tuple, cfg, horizon: float,
    sub_dt: float = 0.1,
) -> list[Leaders]:  # fmt: skip
    """The :class:`Leaders` of each lateral offset of a path: at every ``sub_dt`` up to
    ``horizon`` seconds, the forecast obstacle points (movers where the forecast puts them then,
    static scenery) inside the corridor, the ego box widened by ``cfg.corridor_margin_m`` on each
    side around the shifted path (points are projected onto the unshifted path; the shift at
    their arc length decides whether they lie in the shifted corridor).

    Args:
        scene: the forecast scene.
        path: the :class:`renderworld.planning.candidates.PlanPath` (current ego frame).
        offsets: lateral offsets of the path, metres (left +).
        cfg: the :class:`renderworld.planning.candidates.CheckConfig` (corridor, ramp).
        horizon: seconds.
        sub_dt: seconds between rows.
    """
    s = np.arange(0.0, min(path.length, 80.0), 0.5)
    centre, hd = path.at(s)
    taus = np.arange(0.0, horizon + 1e-9, sub_dt)
    n = len(taus)
    half = EGO_WIDTH / 2 + cfg.corridor_margin_m
    reach = half + max(abs(d) for d in offsets)
    lo, hi = centre.min(0) - reach, centre.max(0) + reach

    def project(p):  # [..., 2] -> arc, lateral offset (metres) relative to the path
        dx = p[..., None, 0] - centre[:, 0]
        dy = p[..., None, 1] - centre[:, 1]
        k = (dx * dx + dy * dy).argmin(-1)
        c, sn = np.cos(hd[k]), np.sin(hd[k])
        rx, ry = p[..., 0] - centre[k, 0], p[..., 1] - centre[k, 1]
        return s[k] + c * rx + sn * ry, -sn * rx + c * ry, c, sn

    static = scene.mover < 0
    sp = scene.points[static]
    sp = sp[((sp >= lo) & (sp <= hi)).all(-1)]
    arc_s, lat_s, _, _ = project(sp)  # static scenery: projected once, standing still
    moving = np.flatnonzero(~static)
    arc_m = np.zeros((n, 0))
    lat_m = np.zeros((n, 0))
    v_m = np.zeros((n, 0))
    if len(moving):
        pts = scene.points_at(np.r_[taus, taus + 0.1])[:, moving]  # [2 T, Qm, 2]
        near = np.flatnonzero(((pts[:n] >= lo) & (pts[:n] <= hi)).all(-1).any(0))
        if len(near):
            p = pts[:n, near]
            vel = (pts[n:, near] - p) / 0.1
            arc_m, lat_m, c, sn = project(p)
            v_m = np.maximum(c * vel[..., 0] + sn * vel[..., 1], 0.0)
    arc = np.concatenate([np.broadcast_to(arc_s, (n, len(arc_s))), arc_m], 1)
    lat = np.concatenate([np.broadcast_to(lat_s, (n, len(lat_s))), lat_m], 1)
    along = np.concatenate([np.zeros((n, len(arc_s))), v_m], 1)
    u = np.clip(arc / max(cfg.ramp_m, 1e-6), 0.0, 1.0)
    ramp = u * u * (3 - 2 * u)
    out = []
    for d in offsets:
        inside = (np.abs(lat - d * ramp) <= half) & (arc >= 0.0)
        keep = inside.any(0)
        out.append(Leaders(np.where(inside, arc, np.inf)[:, keep], along[:, keep], sub_dt))
    return out


def idm_arc(v_now, targets, lead: Leaders, cfg, steps, dt) -> np.ndarray:
    """[F, steps] arc lengths (metres) at each waypoint of IDM runs towards each target speed
    [F] (m/s), each behind the leader its own position and the time give (:class:`Leaders`)."""
    f = len(targets)
    v = np.full(f, v_now, dtype=np.float64)
    s = np.zeros(f)
    v0 = np.maximum(np.asarray(targets, dtype=np.float64), 0.1)
    sub = lead.sub_dt
    n_sub = int(round(dt / sub))
    out = np.empty((f, steps))
    for k in range(steps):
        for j in range(n_sub):
            acc = cfg.a_max * (1 - (v / v0) ** 4)
            gap, v_l = lead.nearest(k * n_sub + j, s + FRONT)
            has = np.isfinite(gap)
            if has.any():
                g = np.maximum(np.where(has, gap, 1.0), 0.05)
                dv = v - v_l
                s_star = cfg.s0 + v * cfg.headway + v * dv / (2 * np.sqrt(cfg.a_max * cfg.b))
                acc = acc - np.where(has, cfg.a_max * (np.maximum(s_star, 0.0) / g) ** 2, 0.0)
            acc = np.maximum(acc, cfg.idm_min_accel)
            v_new = np.maximum(v + acc * sub, 0.0)
            s = s + 0.5 * (v + v_new) * sub
            v = v_new
        out[:, k] = s
    return out


def too_close(s_plan, v_plan, lead: Leaders, cfg, dt) -> bool:
    """Whether the plan (arc lengths [S] and speeds [S] at its waypoints) comes within
    ``cfg.s0 + cfg.cap_gap_s * speed`` of a leader at some waypoint (gap metres, speed m/s)."""
    n_sub = int(round(dt / lead.sub_dt))
    for k in range(len(s_plan)):
        gap, _ = lead.nearest((k + 1) * n_sub, np.array([s_plan[k] + FRONT]))
        if gap[0] < cfg.s0 + cfg.cap_gap_s * v_plan[k]:
            return True
    return False
