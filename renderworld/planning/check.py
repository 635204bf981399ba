"""Candidate plans scored against the world model's own forecast, PDM-style.

Each candidate (:mod:`renderworld.planning.candidates`) is tracked at 10 Hz for the plan's
horizon by the package's kinematic model (:func:`renderworld.planning.tracking.track_plans`),
and the tracked states are scored against the :class:`~renderworld.planning.scene.ForecastScene`
(current ego frame), with NAVSIM's PDM-score structure:

* ``NC`` (no collision): 0 when, at some step, a forecast obstacle point (a mover at its
  forecast position, or static scenery) lies inside the ego box widened by
  :attr:`~renderworld.planning.candidates.CheckConfig.box_margin_m` (and by
  ``vulnerable_margin_m`` more for a pedestrian, cyclist or motorcyclist); a mover point in the
  rear half of the box (something running into the ego from behind) does not count, nor does a
  contact while the ego stands (at most 0.05 m/s: NAVSIM's rule, as in the closed loop);
* ``DAC`` (drivable area): 0 when a corner or edge midpoint of the ego box leaves the drivable
  cells;
* ``EP`` (progress): distance driven over the learned plan's own path length (the model's
  intended progress), clipped to [0, 1]; over the best collision-free on-road candidate's
  when the plan is stalled (:class:`~renderworld.planning.candidates.CheckConfig`); 1 for
  every candidate when that reference is below ``progress_floor_m``. With
  ``progress_along_plan`` the distance is the arc length of the candidate's end projected onto
  the learned plan's path (NAVSIM's progress along the route), unless the plan is stalled;
* ``TTC``: 0 when, at some step with the ego moving, its box carried on at constant velocity
  and heading for up to ``ttc_horizon_s`` meets a forecast obstacle point ahead of it (within
  30 degrees of its heading) that it does not already touch;
* ``C`` (comfort): 0 when the tracked states, following the ego's last second, exceed a NAVSIM
  comfort bound (:mod:`renderworld.planning.comfort`, the closed loop's own signals);
* ``score = NC x DAC x (5 EP + 5 TTC + 2 C) / 12``.

The best candidate has the highest score less ``offset_cost`` per metre of lateral offset and
``change_cost`` per metre of mean distance from the previous plan (with ``change_sideways`` only
across its path; an offset or a change has to
buy safety or progress: no weaving or dithering between equal candidates), the earlier one in
candidate order on ties (the learned plan itself comes first); the learned plan also wins while
it scores above 0 and trails the best by at most ``plan_margin``. A ``pass`` candidate (past a
parked road user, :mod:`renderworld.planning.passing`) pays no offset cost and wins over the
learned plan whenever it is the better: waiting behind a car that will not move is no
progress. When every score is 0 the
candidate that stays on the drivable area and meets an obstacle latest (never, best) is chosen,
then the one with the least lateral offset, then the one driving least: the hardest brake in
its lane (a swerve into the next lane makes a contact the ego's fault).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import EGO_CENTRE_OFFSET, EGO_LENGTH, EGO_WIDTH, KEYFRAME_DT
from renderworld.planning.candidates import Candidates, CheckConfig
from renderworld.planning.comfort import (
    COMFORT_BOUNDS,
    COMFORT_STRIDE,
    COMFORT_WINDOW,
    comfort_signals_fast,
)
from renderworld.planning.kinematics import SIM_DT, KinematicLimits
from renderworld.planning.scene import ForecastScene
from renderworld.planning.tracking import track_plans

__all__ = ["CandidateScores", "comfort_excess", "comfort_ok", "plan_change", "score_candidates"]

_TTC_CONE = np.radians(30.0)
_STOPPED = 0.05  # m/s


@dataclass
class CandidateScores:
    """Every candidate and its scores (``PlanResult.candidates`` of a checked plan).

    Attributes:
        kind: N candidate kinds (``plan``, ``idm``, ``brake``, with ``soft_min_accel`` also
            ``idm_soft``; ``steady_idm``, ``steady_brake``, ... along the ego's steady path).
        offset_m: [N] lateral offsets, metres.
        speed: [N] target speed (m/s) or deceleration (m/s^2, ``brake``).
        waypoints: [N, S, 2] the candidates as proposed, metres, current ego frame.
        states: [N, T, 4] (x, y, yaw, speed) tracked at 10 Hz.
        NC, DAC, EP, TTC, C, score: [N] sub-scores and the aggregate (module docstring).
        progress_m: [N] distance driven (or with ``progress_along_plan`` the arc reached along
            the plan's path), metres.
        first_contact_s: [N] time of the first contact with the forecast (inf: none).
        comfort_excess: [N] the worst comfort quantity as a fraction of its NAVSIM bound (>= 1:
            uncomfortable, C = 0), and ``comfort_worst`` [N] its name.
        choice: [N] what the choice maximises: the score less the offset, change and
            discomfort costs (module docstring); all equal to the score where every score is 0.
        best: index of the chosen candidate.
    """

    kind: list
    offset_m: np.ndarray
    speed: np.ndarray
    waypoints: np.ndarray
    states: np.ndarray
    NC: np.ndarray
    DAC: np.ndarray
    EP: np.ndarray
    TTC: np.ndarray
    C: np.ndarray
    score: np.ndarray
    progress_m: np.ndarray
    first_contact_s: np.ndarray
    choice: np.ndarray
    best: int
    comfort_excess: np.ndarray | None = None
    comfort_worst: list | None = None

    def table(self) -> list[dict]:
        """One dict per candidate (kind, offset, speed and every score), for printing."""
        keys = ("NC", "DAC", "EP", "TTC", "C", "score", "choice", "progress_m", "first_contact_s")
        rows = [
            {"kind": k, "offset_m": float(self.offset_m[i]), "speed": float(self.speed[i]),
             **{n: float(getattr(self, n)[i]) for n in keys}, "best": i == self.best}
            for i, k in enumerate(self.kind)
        ]  # fmt: skip
        if self.comfort_excess is not None:
            for r, x, w in zip(rows, self.comfort_excess, self.comfort_worst):
                r["comfort_excess"], r["comfort_worst"] = float(x), str(w)
        return rows


def comfort_excess(
    states: np.ndarray,
    past: np.ndarray,
    stride: int = COMFORT_STRIDE,
    prefixes_s: tuple[float, ...] = (),
    worst_name: bool = False,
):
    """[N] how far each candidate's worst comfort quantity goes, as a fraction of its NAVSIM
    bound (:mod:`renderworld.planning.comfort`): below 1 is comfortable.

    The closed loop judges windows that start at every plan (every ``stride`` states), so a
    candidate's tracked states [N, T, 4] are judged in each window the ego's past states [n, 4]
    (the last one: now) and the candidate make together: one starting now and one starting at
    each earlier plan within the past (the filters see where the motion comes from and where
    it starts); the quantities are judged from now on.

    ``prefixes_s`` judges, besides, the window that starts now cut after each of these many
    seconds. NAVSIM's filters fit one quadratic over a whole window, which smooths away a brake
    tapped and released; a fit over the first second reads its jerk. Stricter than the closed
    loop's 4 s windows on purpose: the next plans' motion, which fills the rest of those, is
    unknown here, and a candidate whose speed changes abruptly then gives way to a smooth one.

    With ``worst_name`` it also returns, per candidate, the quantity that went furthest (a
    :data:`~renderworld.planning.comfort.COMFORT_BOUNDS` key): ``(excess [N], names [N])``.
    """
    n = states.shape[0]
    past = np.broadcast_to(past[None], (n, *past.shape))
    worst = np.zeros(n)
    which = np.zeros(n, dtype=np.int64)  # index into COMFORT_BOUNDS of the worst quantity
    windows = [(a, COMFORT_WINDOW) for a in range(past.shape[1] - 1, -1, -stride)]
    windows += [(past.shape[1] - 1, int(round(s / SIM_DT)) + 1) for s in prefixes_s]
    for start, length in windows:
        window = np.concatenate([past[:, start:], states], axis=1)[:, :length]
        if window.shape[1] < 5:
            continue
        q = comfort_signals_fast(window)
        k = past.shape[1] - 1 - start
        for j, (name, (lo, hi)) in enumerate(COMFORT_BOUNDS.items()):
            x = q[name][:, k:]
            ratio = np.maximum(np.where(x > 0, x / hi, x / lo), 0.0).max(1)
            outside = ~((x > lo) & (x < hi)).all(1)  # strictly inside, as NAVSIM judges
            value = np.where(outside, np.maximum(ratio, 1.0), ratio)
            which = np.where(value > worst, j, which)
            worst = np.maximum(worst, value)
    if worst_name:
        keys = list(COMFORT_BOUNDS)
        return worst, [keys[j] for j in which]
    return worst


def comfort_ok(states: np.ndarray, past: np.ndarray, stride: int = COMFORT_STRIDE) -> np.ndarray:
    """[N] bool: candidates comfortable by NAVSIM's bounds (:func:`comfort_excess` below 1)."""
    return comfort_excess(states, past, stride) < 1.0


def _box_frames(states: np.ndarray):
    """Box centres [N, T, 2], heading unit vectors u, normals n [N, T, 2] of rear-axle states."""
    yaw = states[..., 2]
    u = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    nrm = np.stack([-np.sin(yaw), np.cos(yaw)], -1)
    return states[..., :2] + EGO_CENTRE_OFFSET * u, u, nrm


def _relevant(scene: ForecastScene, states: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Indices of the obstacle points that come near some candidate state (bounding box)."""
    reach = np.hypot(EGO_LENGTH, EGO_WIDTH) / 2 + 2.0
    lo = states[..., :2].reshape(-1, 2).min(0) - reach - EGO_CENTRE_OFFSET
    hi = states[..., :2].reshape(-1, 2).max(0) + reach + EGO_CENTRE_OFFSET
    pts = scene.points_at(times)  # [T, P, 2]
    near = ((pts >= lo) & (pts <= hi)).all(-1).any(0)
    return np.flatnonzero(near)


def plan_change(waypoints: np.ndarray, previous: np.ndarray, sideways: bool) -> np.ndarray:
    """[N] metres: each candidate's mean distance from the previous plan's waypoints.

    Args:
        waypoints: [N, S, 2] the candidates, current ego frame.
        previous: [S, 2] the previous plan carried on to now, the same frame.
        sideways: only the part across the previous plan's direction at each waypoint (the
            chord through its neighbours; the ego's heading where it stands): a change of speed
            costs nothing, a change of path does.
    """
    prev = np.asarray(previous, dtype=np.float64)
    diff = np.asarray(waypoints, dtype=np.float64) - prev[None]
    if not sideways:
        return np.hypot(diff[..., 0], diff[..., 1]).mean(-1)
    pts = np.concatenate([np.zeros((1, 2)), prev])
    chord = np.gradient(pts, axis=0)[1:]  # [S, 2]
    n = np.hypot(chord[:, 0], chord[:, 1])
    unit = np.where(n[:, None] > 1e-3, chord / np.maximum(n, 1e-3)[:, None], [1.0, 0.0])
    normal = np.stack([-unit[:, 1], unit[:, 0]], axis=-1)
    return np.abs((diff * normal[None]).sum(-1)).mean(-1)


def score_candidates(
    cands: Candidates,
    scene: ForecastScene,
    past: np.ndarray,
    cfg: CheckConfig,
    limits: KinematicLimits | None = None,
    dt: float = KEYFRAME_DT,
    previous: np.ndarray | None = None,
) -> CandidateScores:
    """Track and score candidates (module docstring).

    Args:
        cands: the candidates (``plan`` without offset first).
        scene: the forecast scene.
        past: [n, 4] the ego's recent 10 Hz states (x, y, yaw, speed), current ego frame, the
            last one now (:func:`renderworld.planning.checked.past_states`).
        cfg: the knobs.
        limits: the kinematic model's limits (default :class:`KinematicLimits`).
        dt: seconds between waypoints.
        previous: [S, 2] the previous plan's waypoints carried on to now (metres, current ego
            frame) or None: candidates pay ``cfg.change_cost`` per metre of mean distance to it.
    """
    limits = limits or KinematicLimits()
    wp = cands.waypoints
    n, s = wp.shape[:2]
    steps = int(round(s * dt / SIM_DT))
    speed = float(past[-1, 3])
    start = np.tile([0.0, 0.0, 0.0, speed], (n, 1))
    states, _ = track_plans(start, wp, limits, steps, spline=cfg.spline_tracking)
    n_ttc = int(round(cfg.ttc_horizon_s / SIM_DT))
    times = np.arange(1, steps + n_ttc + 1) * SIM_DT
    keep = _relevant(scene, states, times)
    pts = scene.points_at(times)[:, keep]  # [T + n_ttc, P, 2]
    mover = scene.mover[keep] >= 0
    pad = cfg.box_margin_m + cfg.vulnerable_margin_m * scene.vulnerable[keep]  # [P] metres
    centre, u, nrm = _box_frames(states)
    half_l = EGO_LENGTH / 2 + pad  # [P]
    half_w = EGO_WIDTH / 2 + pad + cfg.side_margin_m
    moving = states[..., 3] > _STOPPED  # [N, T]
    first = np.full(n, np.inf)
    ttc_bad = np.zeros(n, dtype=bool)
    if pts.shape[1]:
        rel = pts[None, :steps] - centre[:, :, None]  # [N, T, P, 2]
        along = (rel * u[:, :, None]).sum(-1)
        lat = (rel * nrm[:, :, None]).sum(-1)
        inside = (np.abs(along) <= half_l) & (np.abs(lat) <= half_w)
        rear = mover[None, None] & (along < 0)
        hit = (inside & ~rear).any(-1) & moving  # [N, T]: a standing ego is not at fault
        t_hit = np.where(hit, np.arange(1, steps + 1)[None] * SIM_DT, np.inf)
        first = t_hit.min(1)
        touching = inside.any(1)  # [N, P] points the box already meets: not a TTC event
        for delta in range(1, n_ttc + 1):
            fut = pts[delta : delta + steps][None]  # [1, T, P, 2]
            c2 = centre + (states[..., 3] * delta * SIM_DT)[..., None] * u
            rel2 = fut - c2[:, :, None]
            a2 = (rel2 * u[:, :, None]).sum(-1)
            l2 = (rel2 * nrm[:, :, None]).sum(-1)
            in2 = (np.abs(a2) <= half_l) & (np.abs(l2) <= half_w)
            ahead = (along > 0) & (np.abs(np.arctan2(lat, np.maximum(along, 1e-9))) <= _TTC_CONE)
            bad = in2 & ahead & ~touching[:, None] & moving[..., None]
            ttc_bad |= bad.any((1, 2))
    corners = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1], [1, 0], [-1, 0], [0, 1], [0, -1]])
    hl = EGO_LENGTH / 2 + cfg.drivable_margin_m
    hw = EGO_WIDTH / 2 + cfg.drivable_margin_m
    box_pts = (centre[:, :, None] + (corners[:, :1] * hl)[None, None] * u[:, :, None]
               + (corners[:, 1:] * hw)[None, None] * nrm[:, :, None])  # fmt: skip
    dac = scene.on_drivable(box_pts).all((1, 2))
    progress = np.concatenate(
        [np.zeros((n, 1)), np.hypot(*np.diff(states[..., :2], axis=1).transpose(2, 0, 1))], 1
    ).sum(1) + np.hypot(*states[:, 0, :2].T)
    ref = cands.reference_m
    if cfg.progress_along_plan and ref is not None and cands.path is not None:
        progress = cands.path.project(states[:, -1, :2])
    nc = np.isinf(first).astype(float)
    if ref is None:  # a stalled plan: the best collision-free on-road candidate's progress
        safe = (nc > 0) & dac
        ref = float(progress[safe].max()) if safe.any() else 0.0
    if ref < cfg.progress_floor_m:
        ep = np.ones(n)
    else:
        ep = np.clip(progress / ref, 0.0, 1.0)
    ttc = (~ttc_bad).astype(float)
    excess, worst = comfort_excess(states, past, prefixes_s=cfg.comfort_prefixes_s, worst_name=True)
    c = (excess < 1.0).astype(float)
    score = nc * dac * (5 * ep + 5 * ttc + 2 * c) / 12
    if score.max() > 0:  # a lateral offset or a change of plan must buy more than it costs
        passing = np.array([k == "pass" for k in cands.kind], dtype=bool)
        cost = np.where(passing, 0.0, cfg.offset_cost * np.abs(cands.offset_m))
        discomfort = cfg.discomfort_cost * np.maximum(excess - 1.0, 0.0)
        cost = cost + discomfort
        if previous is not None and cfg.change_cost:
            cost = cost + cfg.change_cost * plan_change(wp, previous, cfg.change_sideways)
        choice = score - cost
        if not cfg.steady_for_comfort and nc[0] * dac[0] * ttc[0] > 0:  # the plan's path is safe
            steady = np.array([k.startswith("steady") for k in cands.kind])
            choice = np.where(steady, -np.inf, choice)
        best = int(np.argmax(choice))
        plan = choice[0] if cfg.margin_counts_discomfort else score[0] - (cost[0] - discomfort[0])
        if score[0] > 0 and plan >= choice[best] - cfg.plan_margin:
            best = 0  # the learned plan, unless another candidate is clearly better
            if passing.any() and choice[passing].max() > plan:  # or a pass is at all better
                best = int(np.flatnonzero(passing)[np.argmax(choice[passing])])
    else:  # every candidate collides or leaves the road: on the road, latest contact, in its
        # lane, then the hardest brake (a swerve into the next lane is a contact at fault)
        choice = score
        order = np.lexsort((progress, np.abs(cands.offset_m), -np.minimum(first, 1e6),
                            -dac.astype(float)))  # fmt: skip
        best = int(order[0])
    return CandidateScores(
        kind=list(cands.kind), offset_m=cands.offset_m, speed=cands.speed, waypoints=wp,
        states=states, NC=nc, DAC=dac.astype(float), EP=ep, TTC=ttc, C=c, score=score,
        progress_m=progress, first_contact_s=first, choice=choice, best=best,
        comfort_excess=excess, comfort_worst=worst,
    )  # fmt: skip
