"""The Intelligent Driver Model (Treiber) along a path, behind the forecast's leaders.

PDM-Closed (nuPlan, NAVSIM) simulates its proposals with IDM behind the leading agent; here the
leaders are the forecast obstacle points inside the ego's corridor at each moment
(:func:`leaders`): a mover where the forecast puts it then, or static scenery, moving along the
path at its velocity's component, never backwards. A pedestrian who will have crossed is not
waited for; one who will be in the lane is. With ``CheckConfig.anticipate_s`` an obstacle that
will enter the corridor within that many seconds leads already, at its place along the path
now (the privileged rule-based reference's rule): a car cutting in is followed from when its
cut-in is foreseen, not from when it arrives, unless the ego will have passed by then.

Frames: the current ego frame (x forward, y left; metres, seconds, m/s); arc lengths along the
path from the ego's rear axle now.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from renderworld.constants import EGO_CENTRE_OFFSET, EGO_LENGTH, EGO_WIDTH
from renderworld.planning.scene import ForecastScene

__all__ = [
    "BEHIND_M", "FRONT", "PASS_M", "Leaders", "cah_accel", "idm_arc", "idm_arcs", "leaders",
    "too_close",
]  # fmt: skip

FRONT = EGO_CENTRE_OFFSET + EGO_LENGTH / 2  # rear axle -> front bumper, metres
BEHIND_M = 1.0  # corridor points this far behind the front bumper still lead, metres
PASS_M = 2.0  # an anticipated leader is ignored when the ego's rear will be this far past it


@dataclass
class Leaders:
    """Forecast obstacles in the ego's corridor over time, along a path.

    Attributes:
        arc: [T, Q] arc length (metres, from the ego's rear axle now) at which each obstacle
            point lies in the corridor at time ``t * sub_dt`` (inf: outside it then); with
            anticipation, of a point that enters it ``delay`` later, the arc where it enters
            less its travel along the path until then (its place along the path at ``t``).
        speed: [T, Q] the point's velocity component along the path there, m/s (never < 0).
        sub_dt: seconds between rows.
        delay: None, or [T, Q] seconds until the point enters the corridor (0: in it).
        entry: None, or [T, Q] arc length where it enters, metres.
        headway: None, or [Q] IDM time headway behind each point, seconds (None: the
            config's; :mod:`renderworld.planning.relax`).
    """

    arc: np.ndarray
    speed: np.ndarray
    sub_dt: float
    delay: np.ndarray | None = None
    entry: np.ndarray | None = None
    headway: np.ndarray | None = None

    def nearest(
        self, i: int, front: np.ndarray, ego_speed: np.ndarray | float = 0.0,
        with_accel: bool = False,
    ) -> tuple[np.ndarray, ...]:  # fmt: skip
        """(gap [F] metres, speed [F] m/s) of the leader at row ``i`` for front bumpers at arc
        ``front`` [F] (inf, 0 where none): the nearest point ahead, counting points up to
        :data:`BEHIND_M` behind the bumper (they are about to touch it). An anticipated point
        does not lead where the ego, going on at ``ego_speed`` ([F] or one, m/s), will have
        passed where it enters by :data:`PASS_M` when it gets there. ``with_accel``: also its
        acceleration along the path [F] (m/s^2, from the next row's speed; 0 where none)."""
        row = min(i, len(self.arc) - 1)
        if not self.arc[row].size:
            none = (np.full(len(front), np.inf), np.zeros(len(front)))
            return (*none, np.zeros(len(front))) if with_accel else none
        gap, j = self.nearest_index(i, front, ego_speed)
        lead_v, lead_a = self.motion(row, gap, j, with_accel)
        return (gap, lead_v, lead_a) if with_accel else (gap, lead_v)

    def motion(
        self, row: int, gap: np.ndarray, j: np.ndarray, with_accel: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """(speed [F] m/s, acceleration [F] m/s^2 or None without ``with_accel``) along the
        path of the points ``j`` [F] that :meth:`nearest_index` found at ``row`` (0 where the
        gap is inf; the acceleration from the next row's speed)."""
        has = np.isfinite(gap)
        lead_v = np.where(has, self.speed[row][j], 0.0)
        if not with_accel:
            return lead_v, None
        later = self.speed[min(row + 1, len(self.arc) - 1)][j]
        return lead_v, np.where(has, (later - self.speed[row][j]) / self.sub_dt, 0.0)

    def nearest_index(
        self, i: int, front: np.ndarray, ego_speed: np.ndarray | float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """(gap [F] metres, index [F] of the leading point) at row ``i`` (:meth:`nearest`; the
        index is 0 where the gap is inf); the arc must hold at least one point."""
        row = min(i, len(self.arc) - 1)
        arc = self.arc[row]
        ahead = arc[None] > front[:, None] - BEHIND_M  # [F, Q]
        if self.delay is not None:
            rear = front[:, None] - EGO_LENGTH + np.reshape(ego_speed, (-1, 1)) * self.delay[row]
            ahead &= (self.delay[row] == 0) | (rear < self.entry[row] + PASS_M)
        gaps = np.where(ahead, arc[None] - front[:, None], np.inf)
        j = gaps.argmin(1)
        return gaps[np.arange(len(front)), j], j


def leaders(
    scene: ForecastScene, path, offsets: tuple, cfg, horizon: float,
    sub_dt: float = 0.1, mover_headway: np.ndarray | None = None,
) -> list[Leaders]:  # fmt: skip
    """The :class:`Leaders` of each lateral offset of a path: at every ``sub_dt`` up to
    ``horizon`` seconds, the forecast obstacle points (movers where the forecast puts them then,
    static scenery) inside the corridor, the ego box widened by ``cfg.corridor_margin_m`` on each
    side around the shifted path (points are projected onto the unshifted path; the shift at
    their arc length, the ramp of ``cfg.ramp_m`` and ``cfg.quintic_ramp``, decides whether they
    lie in the shifted corridor). With
    ``cfg.anticipate_s`` > 0 a point leads from that many seconds before it enters
    (:class:`Leaders`).

    Args:
        scene: the forecast scene.
        path: the :class:`renderworld.planning.path.PlanPath` (current ego frame).
        offsets: lateral offsets of the path, metres (left +).
        cfg: the :class:`renderworld.planning.candidates.CheckConfig` (corridor, ramp).
        horizon: seconds.
        sub_dt: seconds between rows.
        mover_headway: None, or [M] the IDM time headway behind each mover, seconds
            (:attr:`Leaders.headway`; static scenery keeps ``cfg.headway``).
    """
    s = np.arange(0.0, min(path.length, 80.0), 0.5)
    centre, hd = path.at(s)
    n_rows = len(np.arange(0.0, horizon + 1e-9, sub_dt))
    n_ahead = int(round(max(cfg.anticipate_s, 0.0) / sub_dt))
    taus = np.arange(n_rows + n_ahead) * sub_dt
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
    hw_m = np.zeros(0)
    if len(moving):
        pts = scene.points_at(np.r_[taus, taus + 0.1])[:, moving]  # [2 T, Qm, 2]
        near = np.flatnonzero(((pts[:n] >= lo) & (pts[:n] <= hi)).all(-1).any(0))
        if len(near):
            p = pts[:n, near]
            vel = (pts[n:, near] - p) / 0.1
            arc_m, lat_m, c, sn = project(p)
            v_m = np.maximum(c * vel[..., 0] + sn * vel[..., 1], 0.0)
            if mover_headway is not None:
                hw_m = np.asarray(mover_headway, dtype=np.float64)[scene.mover[moving[near]]]
    arc = np.concatenate([np.broadcast_to(arc_s, (n, len(arc_s))), arc_m], 1)
    lat = np.concatenate([np.broadcast_to(lat_s, (n, len(lat_s))), lat_m], 1)
    along = np.concatenate([np.zeros((n, len(arc_s))), v_m], 1)
    hw = None
    if mover_headway is not None:
        hw = np.concatenate([np.full(len(arc_s), cfg.headway), hw_m])
    u = np.clip(arc / max(cfg.ramp_m, 1e-6), 0.0, 1.0)
    ramp = u * u * u * (10.0 + u * (6.0 * u - 15.0)) if cfg.quintic_ramp else u * u * (3 - 2 * u)
    out = []
    for d in offsets:
        inside = (np.abs(lat - d * ramp) <= half) & (arc >= 0.0)
        keep = inside.any(0)
        inside, a, v = inside[:, keep], arc[:, keep], along[:, keep]
        h = None if hw is None else hw[keep]
        if not n_ahead:
            out.append(Leaders(np.where(inside, a, np.inf), v, sub_dt, headway=h))
            continue
        out.append(replace(_anticipated(inside, a, v, n_rows, n_ahead, sub_dt), headway=h))
    return out


def _anticipated(inside, arc, along, n_rows, n_ahead, sub_dt) -> Leaders:
    """:class:`Leaders` whose row ``i`` holds each point's first entry into the corridor within
    rows ``i ... i + n_ahead`` (inside, arc, along: [n_rows + n_ahead, Q])."""
    q = inside.shape[1]
    eq = np.full((n_rows, q), np.inf)
    speed = np.zeros((n_rows, q))
    delay = np.zeros((n_rows, q))
    entry = np.full((n_rows, q), np.inf)
    cols = np.arange(q)
    for i in range(n_rows):
        window = inside[i : i + n_ahead + 1]
        first = window.argmax(0)  # the first row inside (0 where never: masked below)
        hit = window[first, cols]
        j = i + first
        wait = first * sub_dt
        eq[i] = np.where(hit, arc[j, cols] - along[j, cols] * wait, np.inf)
        speed[i] = np.where(hit, along[j, cols], 0.0)
        delay[i] = np.where(hit, wait, 0.0)
        entry[i] = np.where(hit, arc[j, cols], np.inf)
    return Leaders(eq, speed, sub_dt, delay, entry)


def cah_accel(v, v_l, a_l, gap, a_max) -> np.ndarray:
    """The constant-acceleration heuristic (Kesting, Treiber, Helbing 2010): the acceleration
    [F] (m/s^2) that just avoids a collision if the leader keeps its acceleration ``a_l`` (capped
    at ``a_max``) and neither reacts; ego speed ``v``, leader speed ``v_l`` (m/s), ``gap`` (m)."""
    a_t = np.minimum(a_l, a_max)
    g = np.maximum(gap, 0.05)
    near = v_l * (v - v_l) <= -2.0 * g * a_t
    den = np.maximum(v_l * v_l - 2.0 * g * a_t, 1e-6)
    return np.where(near, v * v * a_t / den, a_t - np.maximum(v - v_l, 0.0) ** 2 / (2.0 * g))


def idm_arc(v_now, targets, lead: Leaders, cfg, steps, dt) -> np.ndarray:
    """[F, steps] arc lengths (metres) at each waypoint of IDM runs towards each target speed
    [F] (m/s), each behind the leader its own position and the time give (:class:`Leaders`).

    With ``cfg.acc_coolness`` c > 0 the runs follow the ACC model (the Enhanced IDM; Kesting,
    Treiber, Helbing 2010) instead: where IDM brakes harder than the constant-acceleration
    heuristic needs (a car cutting in close but not much slower), the acceleration is
    ``(1 - c) a_IDM + c [a_CAH + b tanh((a_IDM - a_CAH) / b)]``: firm, not an emergency stop.
    With ``cfg.idm_plus`` the IDM acceleration is IDM+'s (Schakel, Knoop, van Arem 2010):
    ``a_max min(1 - (v/v0)^4, 1 - (s*/s)^2)``, so a car at its desired speed does not brake for
    a leader farther than the desired gap (IDM's sum brakes for any leader there)."""
    v0 = np.asarray(targets, dtype=np.float64)
    cool = cfg.acc_coolness > 0

    def find(row, front, v):
        r = min(row, len(lead.arc) - 1)
        if not lead.arc[r].size:
            return np.full(len(front), np.inf), np.zeros(len(front)), np.zeros(len(front)), None
        gap, j = lead.nearest_index(row, front, v)
        v_l, a_l = lead.motion(r, gap, j, cool)
        return gap, v_l, a_l, None if lead.headway is None else lead.headway[j]

    return _idm_loop(v_now, v0, find, lead.sub_dt, cfg, steps, dt)


def _idm_loop(v_now, targets: np.ndarray, find, sub: float, cfg, steps, dt) -> np.ndarray:
    """[F, steps] arc lengths of IDM runs from ``v_now`` towards ``targets`` [F] (m/s), each
    behind the leader ``find(row, front bumpers [F], speeds [F])`` gives at leader row ``row``:
    (gap [F] metres, its speed [F] m/s, its acceleration [F] m/s^2 or None without
    ``cfg.acc_coolness``, the time headway behind it [F] seconds or None: ``cfg.headway``)."""
    f = len(targets)
    v = np.full(f, v_now, dtype=np.float64)
    s = np.zeros(f)
    v0 = np.maximum(targets, 0.1)
    n_sub = int(round(dt / sub))
    cool = cfg.acc_coolness
    out = np.empty((f, steps))
    for k in range(steps):
        for j in range(n_sub):
            acc = cfg.a_max * (1 - (v / v0) ** 4)
            gap, v_l, a_l, hw = find(k * n_sub + j, s + FRONT, v)
            has = np.isfinite(gap)
            if has.any():
                g = np.maximum(np.where(has, gap, 1.0), 0.05)
                dv = v - v_l
                t_h = cfg.headway if hw is None else np.where(has, hw, cfg.headway)
                s_star = cfg.s0 + v * t_h + v * dv / (2 * np.sqrt(cfg.a_max * cfg.b))
                inter = cfg.a_max * (np.maximum(s_star, 0.0) / g) ** 2
                if cfg.idm_plus:  # IDM+: the smaller of the free-road and the interaction terms
                    acc = np.where(has, np.minimum(acc, cfg.a_max - inter), acc)
                else:
                    acc = acc - np.where(has, inter, 0.0)
                if cool > 0:
                    cah = cah_accel(v, v_l, a_l, g, cfg.a_max)
                    blend = (1 - cool) * acc + cool * (cah + cfg.b * np.tanh((acc - cah) / cfg.b))
                    acc = np.where(has & (acc < cah), blend, acc)
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
        gap, _ = lead.nearest((k + 1) * n_sub, np.array([s_plan[k] + FRONT]), v_plan[k])
        if gap[0] < cfg.s0 + cfg.cap_gap_s * v_plan[k]:
            return True
    return False


def idm_arcs(v_now, targets: list, leads: list, cfg, steps, dt) -> list:
    """:func:`idm_arc` for several leader sets at once: ``[F_k, steps]`` arc lengths (metres)
    of the IDM runs towards ``targets[k]`` (m/s) behind ``leads[k]`` (:class:`Leaders` of one
    :func:`leaders` call: the same rows), for each k; equal to :func:`idm_arc` run on each, which
    is its reference twin. One loop over the 10 Hz steps serves every run: the check's
    candidates of all lateral offsets in one go."""
    sizes = [len(t) for t in targets]
    if not sum(sizes):
        return [np.empty((0, steps)) for _ in sizes]
    rows = {lead.arc.shape[0] for lead in leads}
    anticipated = {lead.delay is not None for lead in leads}
    if len(rows) > 1 or len(anticipated) > 1:
        raise ValueError("leads: expected the Leaders of one leaders() call (the same rows)")
    q = max(max(lead.arc.shape[1] for lead in leads), 1)
    n = rows.pop()

    def pad(get, fill):
        return np.stack([np.pad(get(lead), ((0, 0), (0, q - lead.arc.shape[1])),
                                constant_values=fill) for lead in leads])  # fmt: skip

    arc = pad(lambda ld: ld.arc, np.inf)
    speed = pad(lambda ld: ld.speed, 0.0)
    delay = pad(lambda ld: ld.delay, 0.0) if anticipated.pop() else None
    entry = pad(lambda ld: ld.entry, np.inf) if delay is not None else None
    headway = None
    if any(ld.headway is not None for ld in leads):

        def per_point(ld):  # [T, Q] the headway of each point (constant over the rows)
            h = np.full(ld.arc.shape[1], cfg.headway) if ld.headway is None else ld.headway
            return np.broadcast_to(h, ld.arc.shape)

        headway = pad(per_point, cfg.headway)[:, 0]  # [L, q]
    run = np.repeat(np.arange(len(leads)), sizes)  # [F] each row's leader set
    rng = np.arange(len(run))
    cool = cfg.acc_coolness > 0

    def find(i, front, v):  # Leaders.nearest, each row against its own leader set
        row = min(i, n - 1)
        a_row = arc[run, row]  # [F, Q]
        ahead = a_row > front[:, None] - BEHIND_M
        if delay is not None:
            d_row = delay[run, row]
            rear = front[:, None] - EGO_LENGTH + v[:, None] * d_row
            ahead &= (d_row == 0) | (rear < entry[run, row] + PASS_M)
        gaps = np.where(ahead, a_row - front[:, None], np.inf)
        idx = gaps.argmin(1)
        gap = gaps[rng, idx]
        has = np.isfinite(gap)
        v_l = np.where(has, speed[run, row][rng, idx], 0.0)
        hw = None if headway is None else headway[run, idx]
        if not cool:
            return gap, v_l, None, hw
        later = speed[run, min(row + 1, n - 1)][rng, idx]
        a_l = np.where(has, (later - speed[run, row][rng, idx]) / leads[0].sub_dt, 0.0)
        return gap, v_l, a_l, hw

    v0 = np.concatenate([np.asarray(t, dtype=np.float64) for t in targets])
    out = _idm_loop(v_now, v0, find, leads[0].sub_dt, cfg, steps, dt)
    return np.split(out, np.cumsum(sizes)[:-1])
