"""Interaction scenarios: an ego speed/path profile plus the scripted agent it reacts to.

Each behaviour of :data:`INTERACTIONS` places one agent explicitly (not by rejection sampling)
and times the ego around it, so that

* the agent never overlaps the ego's actual route (the :func:`clear_of_ego` margins, 0.1 s
  steps over the whole scene), and
* a constant-velocity (CV) extrapolation of the ego taken when it starts to react (its last
  0.5 s displacement repeated six times, box heading along that displacement, box centred at the
  rear-axle waypoint as in the planning collision metric) overlaps the agent's box at one of the
  next six keyframes (:func:`cv_hits`).

Parameters are drawn from the scene generator; a draw that fails either check is redrawn (up to
:data:`MAX_TRIES` times), so a seed fixes the scene. Frames: scene frame (metres, x east, y north,
the ego starts at the origin heading +x); times in seconds from the scene start.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import EGO_LENGTH, EGO_WIDTH, FUTURE_FRAMES, KEYFRAME_DT
from renderworld.sim.agents import Path, Trajectory, rects_overlap
from renderworld.sim.layout import EGO_CENTRE_OFFSET, EgoPlan, ego_trajectory
from renderworld.sim.objects import SimObject, make_object
from renderworld.sim.roads import Road
from renderworld.sim.scene import INTERACTIONS, OBJECT_CATEGORIES, SceneSpec

__all__ = ["INTERACTIONS", "MAX_TRIES", "CV_DEPTH", "plan_interaction", "cv_hits", "clear_of_ego"]

MAX_TRIES = 40
CV_DEPTH = 0.3  # metres the CV box must reach into the agent's box
_FRONT = EGO_CENTRE_OFFSET + EGO_LENGTH / 2  # rear axle -> front bumper, metres
_BACK = EGO_LENGTH / 2 - EGO_CENTRE_OFFSET  # rear axle -> rear bumper, metres
_EGO_MARGIN = np.array([EGO_LENGTH / 2 + 0.5, EGO_WIDTH / 2 + 0.3])  # as traffic._accept


def _ss(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


def integrate_speed(times: np.ndarray, v0: float, target) -> tuple[np.ndarray, np.ndarray]:
    """Arc length [T] (0 at t = 0) and speed [T] of a rate-limited speed profile.

    Args:
        times: [T] seconds, increasing.
        v0: speed before the first sample, m/s.
        target: ``target(t, s) -> (speed m/s, accel m/s^2, decel m/s^2)``, with ``s`` the arc
            length counted from the position at t = 0 (metres along the path, as the builders'
            positions are); the samples before t = 0 run at ``v0`` when the target asks for no
            change there, which every builder's does.
    """
    v = np.empty(len(times))
    s = np.zeros(len(times))
    s_at_zero = v0 * max(0.0, -float(times[0]))  # arc length from times[0] to t = 0 at v0
    sp = v0
    v[0] = sp
    for i in range(1, len(times)):
        dt = times[i] - times[i - 1]
        goal, acc, dec = target(times[i - 1], s[i - 1] - s_at_zero)
        new = float(np.clip(goal, sp - dec * dt, sp + acc * dt))
        s[i] = s[i - 1] + 0.5 * (sp + new) * dt
        sp = new
        v[i] = sp
    return s - np.interp(0.0, times, s), v


def xy_trajectory(times: np.ndarray, xy: np.ndarray) -> Trajectory:
    """Trajectory through points [T, 2] with yaw along the motion (kept while standing)."""
    d = np.gradient(xy, times, axis=0)
    moving = np.hypot(*d.T) > 0.05
    yaw = np.arctan2(d[:, 1], d[:, 0])
    if moving.any():
        idx = np.where(moving, np.arange(len(times)), -1)
        idx = np.maximum.accumulate(idx)
        idx[idx < 0] = int(np.argmax(moving))
        yaw = yaw[idx]
    else:
        yaw = np.zeros(len(times))
    return Trajectory(times, xy, yaw)


def cv_hits(ego: Trajectory, agent: Trajectory, agent_half, k: int, depth: float = 0.0) -> bool:
    """Whether the CV extrapolation of the ego from keyframe ``k`` overlaps the agent.

    The last 0.5 s displacement is repeated for the next :data:`FUTURE_FRAMES` keyframes; the
    ``EGO_LENGTH x EGO_WIDTH`` box is centred at each rear-axle waypoint with its heading along
    the displacement (the current yaw when standing), as the planning collision metric does.
    ``depth`` (metres) shrinks the ego box on every side, so that only an overlap that deep
    counts (the metric rasterises boxes on 0.5 m cells and misses grazing contacts).
    """
    t = k * KEYFRAME_DT
    (p0, _), (p1, yaw) = ego.pose(t - KEYFRAME_DT), ego.pose(t)
    d = p1 - p0
    hd = float(np.arctan2(d[1], d[0])) if np.hypot(*d) >= 0.05 else float(yaw)
    j = np.arange(1, FUTURE_FRAMES + 1)
    ac, ay = agent.pose(t + j * KEYFRAME_DT)
    half = [EGO_LENGTH / 2 - depth, EGO_WIDTH / 2 - depth]
    return bool(rects_overlap(p1 + j[:, None] * d, hd, half, ac, ay, agent_half).any())


def clear_of_ego(ego: Trajectory, obj: SimObject, duration: float, margin: float = 0.25) -> bool:
    """Whether ``obj`` never overlaps the ego's box (with the traffic margins), 0.1 s steps."""
    t = np.arange(-0.5, duration + 3.5, 0.1)
    xy, yaw = ego.pose(t)
    ec = xy + EGO_CENTRE_OFFSET * np.stack([np.cos(yaw), np.sin(yaw)], -1)
    c, y = obj.trajectory.pose(t)
    return not rects_overlap(c, y, obj.footprint_half() + margin, ec, yaw, _EGO_MARGIN).any()


def plan_interaction(
    plan: EgoPlan, spec: SceneSpec, road: Road, times: np.ndarray, keyframes: int, rng
) -> None:
    """Time the ego of an interaction behaviour and script its agent.

    Fills ``plan.trajectory`` (and ``plan.path`` for ``overtake_parked``) and appends the
    agent to ``plan.scripted``.

    Args:
        plan: the ego plan from :func:`renderworld.sim.layout.plan_ego` (path set).
        spec: the scene (``spec.behaviour`` in :data:`INTERACTIONS`).
        road: road 0 of the network (the ego's road).
        times: [T] dense sample times, seconds.
        keyframes: keyframes in the scene (2 Hz).
        rng: the scene generator.

    Raises:
        ValueError: naming ``behaviour`` when no draw satisfies both checks (e.g. too slow).
    """
    duration = (keyframes - 1) * KEYFRAME_DT
    make = _BUILDERS[spec.behaviour]
    k_lo, k_hi = 4, keyframes - 1 - FUTURE_FRAMES
    for _ in range(MAX_TRIES):
        drawn = make(plan, spec, road, times, duration, rng)
        if drawn is None:  # no keyframe of this draw can show the conflict
            continue
        path, ego, agent = drawn
        if not clear_of_ego(ego, agent, duration, 0.1 if agent.label == 2 else 0.25):
            continue
        half = agent.footprint_half()
        if any(cv_hits(ego, agent.trajectory, half, k, CV_DEPTH) for k in range(k_lo, k_hi + 1)):
            plan.path, plan.trajectory = path, ego
            plan.scripted.append(agent)
            return
    raise ValueError(
        f"scene.behaviour: could not script {spec.behaviour!r} at speed {spec.speed} m/s with "
        f"{keyframes} keyframes; expected a faster ego or more keyframes"
    )


def _lane_y(plan: EgoPlan) -> float:
    return -plan.lane_offset


def _car(rng, trucks: float = 0.15) -> tuple[str, tuple[float, float, float]]:
    cat = "vehicle.truck" if rng.random() < trucks else "vehicle.car"
    w, ln, h = OBJECT_CATEGORIES[cat]
    return cat, (w, ln * rng.uniform(0.93, 1.07), h * rng.uniform(0.95, 1.05))


def _lead_brake(plan, spec, road, times, duration, rng):
    """A lead car in the ego lane brakes hard to a stop; the ego stops a few metres behind."""
    v = float(spec.speed)
    a_l, a_e = rng.uniform(3.5, 5.0), rng.uniform(2.5, 3.5)
    react, gap = rng.uniform(0.5, 0.9), rng.uniform(2.0, 3.5)  # s; m bumper to bumper
    t_b = duration * rng.uniform(0.2, 0.32)
    cat, size = _car(rng)
    # Initial gap = final gap + what closes while the ego reacts and brakes more gently than
    # the lead; the lead is never faster than the ego, so the final gap is the smallest.
    gap0 = gap + v * react + 0.5 * v * v * (1 / a_e - 1 / a_l)
    t_stop = t_b + react + v / a_e
    t_go_l = t_stop + rng.uniform(1.5, 3.0)
    t_go_e = t_go_l + rng.uniform(0.8, 1.4)

    def lead(t, s):
        return (0.0, 1.5, a_l) if t_b <= t < t_go_l else (v, 1.5, a_l)

    def ego(t, s):
        return (0.0, 1.5, a_e) if t_b + react <= t < t_go_e else (v, 1.5, a_e)

    s_e, _ = integrate_speed(times, v, ego)
    s_l, _ = integrate_speed(times, v, lead)
    s_l += _FRONT + gap0 + size[1] / 2
    ego_traj = ego_trajectory(plan.path, s_e, times)
    y = _lane_y(plan)
    xy = np.stack([s_l, np.full_like(s_l, y)], -1)
    agent = make_object("scn_lead", cat, size, xy_trajectory(times, xy), rng, moving=True)
    return plan.path, ego_traj, agent


def _cut_in(plan, spec, road, times, duration, rng):
    """A slower car in the adjacent lane merges just ahead; the ego slows to its speed."""
    v = float(spec.speed)
    v_c = v * rng.uniform(0.35, 0.6)
    a_e, react, gap = rng.uniform(2.0, 3.5), rng.uniform(0.4, 0.8), rng.uniform(4.0, 7.0)
    t_m, t_merge = duration * rng.uniform(0.2, 0.3), rng.uniform(2.0, 3.0)
    cat, size = _car(rng, trucks=0.1)
    dv = v - v_c
    g_m = gap + dv * react + dv * dv / (2 * a_e)  # bumper gap when the merge starts

    def ego(t, s):
        return (v_c, 1.5, a_e) if t >= t_m + react else (v, 1.5, a_e)

    s_e, _ = integrate_speed(times, v, ego)
    x_m = v * t_m + _FRONT + g_m + size[1] / 2
    x = x_m + v_c * (times - t_m)
    y_e = _lane_y(plan)
    y_c = y_e + (road.lane_width if y_e < -road.lane_width else -road.lane_width)
    y = y_c + (y_e - y_c) * _ss((times - t_m) / t_merge)
    agent = make_object("scn_cutin", cat, size, xy_trajectory(times, np.stack([x, y], -1)), rng,
                        moving=True)  # fmt: skip
    return plan.path, ego_trajectory(plan.path, s_e, times), agent


def _ped_crossing(plan, spec, road, times, duration, rng):
    """A pedestrian crosses ahead; the ego brakes, waits until it has passed, then goes."""
    v = float(spec.speed)
    a_e, v_p = rng.uniform(2.0, 3.5), rng.uniform(1.1, 1.6)
    t_b = duration * rng.uniform(0.2, 0.32)
    s_stop = v * t_b + v * v / (2 * a_e)
    k = int(np.ceil((t_b + 0.2) / KEYFRAME_DT))
    t_k = k * KEYFRAME_DT

    def brake(t, s):
        return (0.0, 1.5, a_e) if t >= t_b else (v, 1.5, a_e)

    # The crossing line goes where the CV extrapolation from keyframe k is at a future keyframe,
    # 2-5 m beyond the ego's front bumper once it stands.
    s_b, _ = integrate_speed(times, v, brake)
    sk, sk0 = np.interp(t_k, times, s_b), np.interp(t_k - KEYFRAME_DT, times, s_b)
    cv = sk + np.arange(1, FUTURE_FRAMES + 1) * (sk - sk0)
    lo, hi = s_stop + _FRONT + 0.3 + 2.0, s_stop + _FRONT + 0.3 + 5.0
    ok = np.nonzero((cv > lo - 1.0) & (cv < hi + 1.0))[0]
    j = int(ok[rng.integers(len(ok))]) if len(ok) else int(np.argmin(np.abs(cv - lo)))
    s_line = float(np.clip(cv[j] + rng.uniform(-1.0, 1.0), lo, hi))
    t_star = t_k + (j + 1) * KEYFRAME_DT
    y_e = _lane_y(plan)
    kerb = road.half_width + road.sidewalk * 0.5
    side = -1.0 if rng.random() < 0.7 else 1.0  # start on the ego's kerb side (y < 0) mostly
    y0, y1 = side * kerb, -side * kerb
    walk = np.sign(y1 - y0)
    t0 = t_star - abs(y_e + rng.uniform(-0.4, 0.4) - y0) / v_p
    y = y0 + walk * np.clip((times - t0) * v_p, 0.0, 2 * kerb)
    clear = y_e + walk * (EGO_WIDTH / 2 + 0.3 + 1.3)
    t_clear = t0 + abs(clear - y0) / v_p
    t_go = max(t_b + v / a_e + rng.uniform(1.0, 2.0), t_clear + rng.uniform(0.3, 0.8))

    def ego(t, s):
        return (0.0, 1.5, a_e) if t_b <= t < t_go else (v, 1.5, a_e)

    s_e, _ = integrate_speed(times, v, ego)
    size = OBJECT_CATEGORIES["human.pedestrian.adult"]
    size = (size[0], size[1], rng.uniform(1.55, 1.9))
    xy = np.stack([np.full_like(y, s_line), y], -1)
    agent = make_object("scn_ped", "human.pedestrian.adult", size, xy_trajectory(times, xy), rng,
                        moving=True)  # fmt: skip
    return plan.path, ego_trajectory(plan.path, s_e, times), agent


def _turn_oncoming(plan, spec, road, times, duration, rng):
    """Unprotected left turn: the ego creeps into the junction, waits for an oncoming car, turns."""
    v, v_o = float(spec.speed), rng.uniform(7.0, 11.0)
    a_e = rng.uniform(1.5, 2.5)
    cat, size = _car(rng, trucks=0.0)
    y_l = road.lane_width * (road.lanes - 0.5)  # outer oncoming lane centre
    path = plan.path
    s_grid = np.arange(0.0, path.length, 0.2)
    xy, hd = path.at(s_grid)
    box = _box_max_y(xy, hd)
    s_wait = float(s_grid[np.argmax(box > y_l - size[0] / 2 - 1.0)] - 0.2)
    t_b = (s_wait - v * v / (2 * a_e)) / v
    t_stop = t_b + v / a_e

    def brake(t, s):
        return (0.0, 1.5, a_e) if t >= t_b else (v, 1.5, a_e)

    s_b, v_b = integrate_speed(times, v, brake)
    ego_b = ego_trajectory(path, s_b, times)
    # Anchor the car where the CV extrapolation of a turning, still-moving keyframe goes.
    ks = [k for k in range(4, int(duration / KEYFRAME_DT) - FUTURE_FRAMES + 1)
          if t_b < k * KEYFRAME_DT < t_stop - 0.3]  # fmt: skip
    if not ks:
        return None
    k = ks[-1 - int(rng.integers(min(2, len(ks))))]
    t_k = k * KEYFRAME_DT
    (p0, _), (p1, _) = ego_b.pose(t_k - KEYFRAME_DT), ego_b.pose(t_k)
    d = p1 - p0
    j = np.arange(1, FUTURE_FRAMES + 1)
    cvy = p1[1] + j * d[1]
    reach = np.nonzero(cvy + EGO_WIDTH / 2 > y_l - size[0] / 2 + 0.3)[0]
    if not len(reach):
        return None
    jj = int(reach[min(int(rng.integers(2)), len(reach) - 1)])
    x_anchor = p1[0] + (jj + 1) * d[0] + rng.uniform(-1.0, 1.0)
    x = x_anchor - v_o * (times - (t_k + (jj + 1) * KEYFRAME_DT))
    # The ego goes once the car's rear is past everything the turn sweeps near its lane.
    zone = box > y_l - size[0] / 2 - 1.5
    x_min = float(xy[zone, 0].min()) - EGO_LENGTH
    t_clear = float(np.interp(-(x_min - size[1] / 2 - 1.0), -x, times))
    t_go = max(t_stop + rng.uniform(0.5, 1.0), t_clear + rng.uniform(0.3, 0.8))
    arc_end = s_wait + 25.0
    v_turn = min(v, 5.5)

    def ego(t, s):
        if t_b <= t < t_go:
            return (0.0, 1.5, a_e)
        return (v_turn if t >= t_go and s < arc_end else v, 1.5, a_e)

    s_e, _ = integrate_speed(times, v, ego)
    xy_car = np.stack([x, np.full_like(x, y_l)], -1)
    agent = make_object("scn_oncoming", cat, size, xy_trajectory(times, xy_car), rng, moving=True)
    return path, ego_trajectory(path, s_e, times), agent


def _box_max_y(xy: np.ndarray, hd: np.ndarray) -> np.ndarray:
    """Largest y [N] of the ego box (sim convention) at rear-axle poses [N, 2], headings [N]."""
    c = xy[:, 1] + EGO_CENTRE_OFFSET * np.sin(hd)
    return c + EGO_LENGTH / 2 * np.abs(np.sin(hd)) + EGO_WIDTH / 2 * np.abs(np.cos(hd))


def _overtake_parked(plan, spec, road, times, duration, rng):
    """A car stands in the ego lane; the ego slows, swerves into the next lane and back."""
    v = float(spec.speed)
    cat, size = _car(rng, trucks=0.25)
    kerb_off = rng.uniform(0.0, 0.5)  # parked slightly towards the kerb, metres
    lw = road.lane_width
    need = size[0] / 2 + EGO_WIDTH / 2 + 0.55 + 0.45 - kerb_off  # lateral clearance, metres
    u_grid = np.linspace(0, 1, 401)
    u_c = float(np.interp(need / lw, _ss(u_grid), u_grid))
    x1 = v * duration * rng.uniform(0.2, 0.3)
    l1 = max(2.2 * v, 12.0) * rng.uniform(1.0, 1.15)
    l2 = l1 * rng.uniform(1.0, 1.3)
    x_rear = x1 + u_c * l1 + _FRONT + rng.uniform(0.5, 2.5)
    x_car = x_rear + size[1] / 2
    x_front = x_rear + size[1]
    x3 = x_front + _BACK + 0.8 - (1.0 - u_c) * l2 + rng.uniform(0.0, 2.0)
    v_s = v * rng.uniform(0.6, 0.85)

    def lateral(s):
        return lw * (_ss((s - x1) / l1) - _ss((s - x3) / l2))

    path = Path(plan.path.xy).offset(lateral)

    def ego(t, s):
        slow = x1 - v <= s <= x_front + 5.0
        return (v_s if slow else v, 1.2, 2.0)

    s_e, _ = integrate_speed(times, v, ego)
    y = _lane_y(plan) - kerb_off
    traj = Trajectory.fixed(np.array([-1.0, duration + 5.0]), x_car, y, 0.0)
    agent = make_object("scn_parked", cat, size, traj, rng)
    return path, ego_trajectory(path, s_e, times), agent


_BUILDERS = {
    "lead_brake": _lead_brake,
    "cut_in": _cut_in,
    "ped_crossing": _ped_crossing,
    "turn_oncoming": _turn_oncoming,
    "overtake_parked": _overtake_parked,
}
