"""The forecast-checked plan: hand-made scenes on the demo's coarse grid (1.6 m voxels).

The ego drives along +x at 10 m/s; each history frame is drawn in its own ego frame. The
learned plan is replaced by a hand-made one, so every case knows what the check must do.
"""

from dataclasses import replace

import numpy as np
import pytest

from renderworld.constants import FREE_ID, OCC3D_CLASSES, get_grid
from renderworld.planning.candidates import CheckConfig, PlanPath
from renderworld.planning.checked import check_plan, past_states
from renderworld.planning.scene import forecast_scene

GRID = get_grid("coarse")
ROAD, SIDEWALK = OCC3D_CLASSES.index("driveable_surface"), OCC3D_CLASSES.index("sidewalk")
CAR, PED = OCC3D_CLASSES.index("car"), OCC3D_CLASSES.index("pedestrian")
V, DT, H = 10.0, 0.5, 5
TIMES = (np.arange(H) - (H - 1)) * DT  # -2.0 ... 0.0 s


def _cell(x, y):
    g = GRID
    return (int(np.floor((x - g.range_min[0]) / g.voxel_size[0])),
            int(np.floor((y - g.range_min[1]) / g.voxel_size[1])))  # fmt: skip


def history(objects=(), road_half_width=8.0):
    """History occupancy [H, X, Y, Z] and poses [H, 3] of the ego at V m/s along +x.

    ``objects``: (class, world_xy(t) -> [2] metres at time t (s, 0 = now), (cells x, cells y)).
    """
    occ = np.full((H, *GRID.shape), FREE_ID, dtype=np.uint8)
    ys = GRID.range_min[1] + (np.arange(GRID.shape[1]) + 0.5) * GRID.voxel_size[1]
    occ[:, :, :, 0] = np.where(np.abs(ys) < road_half_width, ROAD, SIDEWALK)[None, None]
    poses = np.stack([V * TIMES, np.zeros(H), np.zeros(H)], 1)
    for k, t in enumerate(TIMES):
        for cls, where, (nx, ny) in objects:
            wx, wy = where(t)
            ix, iy = _cell(wx - poses[k, 0], wy)
            occ[k, ix : ix + nx, iy : iy + ny, :2] = cls
    return occ, poses


def straight_plan(speed=V, steps=6):
    t = np.arange(1, steps + 1) * DT
    return np.stack([speed * t, np.zeros(steps), np.zeros(steps)], 1)


def test_a_free_road_keeps_the_learned_plan_exactly():
    occ, poses = history()
    plan = straight_plan()
    out = check_plan(occ, poses, plan, GRID)
    c = out.candidates
    assert c.best == 0 and c.kind[0] == "plan" and c.offset_m[0] == 0.0
    np.testing.assert_array_equal(out.trajectory, plan[:, :2].astype(np.float32))
    assert c.NC[0] == 1 and c.DAC[0] == 1 and c.EP[0] == 1 and c.TTC[0] == 1
    assert len(c.table()) == len(c.kind) > 20 and c.table()[0]["best"]
    assert set(out.timings) == {"scene", "candidates", "scoring", "check"}


def test_a_parked_car_blocking_the_road_is_stopped_for():
    car_x = 28.0  # world x of the car's rear, 28 m ahead of the ego now; it blocks the road
    occ, poses = history([(CAR, lambda t: (car_x, -2.4), (3, 3))], road_half_width=3.5)
    plan = straight_plan()
    out = check_plan(occ, poses, plan, GRID)
    c = out.candidates
    # The plan as is (30 m in 3 s) would hit it: its own candidate is held back behind it.
    assert c.waypoints[0, -1, 0] < plan[-1, 0] - 5.0
    assert c.NC[c.best] == 1 and c.best == int(np.argmax(c.choice))
    paid = np.array([k != "pass" for k in c.kind])  # a pass pays no offset cost (test_passing)
    cost = CheckConfig().offset_cost * np.abs(c.offset_m) * paid
    assert (c.choice <= c.score - cost + 1e-12).all()
    assert out.trajectory[:, 0].max() + 1.1 + 2.042 < car_x  # the box stops short of the car
    np.testing.assert_array_equal(out.trajectory, c.waypoints[c.best].astype(np.float32))


def test_a_crossing_pedestrian_is_tracked_at_walking_speed_and_braked_for():
    walk = 1.2  # m/s: slower than one coarse voxel (1.6 m) per second
    ped = (PED, lambda t: (18.0, -2.4 + walk * t), (1, 1))  # seen in all five frames
    occ, poses = history([ped], road_half_width=2.0)  # a 3.2 m road: no room to pass it
    scene = forecast_scene(occ, poses, GRID, 6)
    (track,) = scene.tracks
    assert track.moving and track.velocity[1] == pytest.approx(walk, abs=0.5)
    out = check_plan(occ, poses, straight_plan(), GRID)
    c = out.candidates
    assert c.NC[c.best] == 1 and c.TTC[c.best] == 1
    assert c.progress_m[c.best] < 20.0  # the plan as is drives 30 m, past the crossing


def test_a_plan_off_the_road_fails_the_drivable_area():
    occ, poses = history(road_half_width=3.0)
    t = np.arange(1, 7) * DT
    swerve = np.stack([V * t, 1.5 * t * t, np.zeros(6)], 1)  # 13.5 m to the left at 3 s
    swerve[:, 2] = np.arctan2(np.gradient(swerve[:, 1]), np.gradient(swerve[:, 0]))
    c = check_plan(occ, poses, swerve, GRID).candidates
    assert c.DAC[0] == 0 and c.score[0] == 0


def test_past_states_follow_the_history_and_give_the_speed():
    occ, poses = history()
    past = past_states(poses)
    np.testing.assert_allclose(past[:, 3], V, atol=1e-9)
    np.testing.assert_allclose(past[:, 0], np.round(np.arange(-1.0, 1e-9, 0.1), 9) * V, atol=1e-9)


def test_paths_and_config_are_validated():
    path = PlanPath(np.array([[0.0, 0.0], [5.0, 0.0]]), extend_m=10.0)
    np.testing.assert_allclose(path.at(np.array([12.0]))[0], [[12.0, 0.0]])
    occ, poses = history()
    with pytest.raises(ValueError, match="plan_poses"):
        check_plan(occ, poses, np.zeros((6, 2)), GRID)
    with pytest.raises(ValueError, match="history_poses"):
        check_plan(occ, poses[:, :2], straight_plan(), GRID)
    assert CheckConfig().offsets_m[0] == 0.0  # the learned path itself comes first


@pytest.mark.parametrize("quintic", [False, True])
def test_offsets_are_reached_over_the_ramp_and_the_quintic_one_starts_straight(quintic):
    path = PlanPath(np.array([[0.0, 0.0], [30.0, 0.0]]), extend_m=10.0)
    s = np.arange(0.0, 16.0, 0.5)
    y = path.offset(s, 2.0, 12.0, quintic)[:, 1]
    assert y[0] == 0.0 and np.all(np.diff(y) >= 0) and np.allclose(y[s >= 12.0], 2.0)
    assert y[s == 6.0][0] == pytest.approx(1.0)  # half way at half the ramp (both are symmetric)
    y0 = path.offset(np.array([0.0, 0.1, 0.2]), 2.0, 12.0, quintic)[:, 1]
    curvature_start = (y0[2] - 2 * y0[1] + y0[0]) / 0.01  # second difference, 1/m
    cubic_start = 6 * 2.0 / 12.0**2  # the cubic's d'' at 0
    if quintic:
        assert abs(curvature_start) < 0.15 * cubic_start
    else:
        assert curvature_start > 0.5 * cubic_start


def test_a_new_plan_starts_on_the_previous_one_and_ends_on_its_own():
    from renderworld.planning.checked import blend_with_previous

    plan = straight_plan()
    previous = plan[:, :2] + [0.0, 1.2]  # the last plan ran 1.2 m to the left
    out = blend_with_previous(plan, previous)
    np.testing.assert_allclose(out[-1, :2], plan[-1, :2])  # the far end: the new plan
    np.testing.assert_allclose(out[0, :2], [5.0, 1.0])  # the near end: mostly the previous
    assert (np.diff(out[:, 1]) < 0).all()  # one smooth way from the one to the other
    assert out[1:, 2].max() < 0  # heading along the blended path: back to the right


def test_a_stalled_plan_gets_candidates_at_the_cruise_speed():
    occ, poses = history()
    poses[:, 0] = 0.0  # the ego stands (stopped for something that has gone)
    creep = straight_plan(speed=0.5)
    c = check_plan(occ, poses, creep, GRID, cruise_speed=10.0).candidates
    assert max(c.speed[np.array(c.kind) == "idm"]) == pytest.approx(10.0)
    assert c.progress_m[c.best] > 3 * c.progress_m[0]  # goes on instead of creeping
    c = check_plan(occ, poses, creep, GRID).candidates  # no cruise speed known: it creeps
    assert max(c.speed[np.array(c.kind) == "idm"]) == pytest.approx(0.5)


def test_a_brake_comfortable_over_a_long_window_is_not_when_the_window_starts_now():
    from renderworld.planning.check import comfort_ok

    past = np.stack([np.arange(-10, 1) * 1.0, np.zeros(11), np.zeros(11), np.full(11, 10.0)], 1)

    def brake(a):  # a m/s^2 for 0.5 s from 10 m/s, then on at that speed: [1, 30, 4]
        v = np.full(30, 10.0 - 0.5 * a)
        v[:5] = 10.0 - a * np.arange(1, 6) * 0.1
        return np.stack([np.cumsum(v * 0.1), np.zeros(30), np.zeros(30), v], 1)[None]

    # The closed loop judges a window that starts at this plan too: 5 m/s^2 breaks the
    # -4.05 m/s^2 bound there, though a window with the last second before it smooths it away.
    assert comfort_ok(brake(3.0), past).all() and not comfort_ok(brake(5.0), past).any()


def test_a_short_brake_is_judged_on_the_start_of_the_window_that_starts_now():
    from renderworld.planning.check import comfort_excess

    past = np.stack([np.arange(-10, 1) * 1.0, np.zeros(11), np.zeros(11), np.full(11, 10.0)], 1)

    def tap(a, steps):  # a m/s^2 for `steps` x 0.1 s from 10 m/s, then on at that speed
        v = np.full(30, 10.0 - a * steps * 0.1)
        v[:steps] = 10.0 - a * np.arange(1, steps + 1) * 0.1
        return np.stack([np.cumsum(v * 0.1), np.zeros(30), np.zeros(30), v], 1)[None]

    prefixes = (1.0, 1.5, 2.0, 2.5)
    # A 3 m/s^2 brake released after 0.3 s: NAVSIM's fit over the whole window smooths its
    # jerk away; the window's first second does not.
    assert comfort_excess(tap(3.0, 3), past)[0] < 1.0
    assert comfort_excess(tap(3.0, 3), past, prefixes_s=prefixes)[0] > 1.0
    # Cruising on stays comfortable however it is cut.
    assert comfort_excess(tap(0.0, 3), past, prefixes_s=prefixes)[0] < 0.05


def test_a_plan_that_taps_the_brake_gives_way_to_a_smooth_speed_profile():
    t = np.arange(1, 31) * 0.1  # 2 m/s^2 for 0.5 s from 10 m/s, then on at 9 m/s
    x = np.cumsum(np.where(t <= 0.5, V - 2.0 * t, V - 1.0) * 0.1)
    plan = np.stack([x[4::5], np.zeros(6), np.zeros(6)], 1)
    occ, poses = history()
    strict = check_plan(  # without the plan margin, which would keep a plan this close
        occ, poses, plan, GRID, CheckConfig(comfort_prefixes_s=(1.0, 2.0), plan_margin=0.0)
    ).candidates
    loose = check_plan(occ, poses, plan, GRID).candidates  # the default: NAVSIM's windows only
    assert strict.kind == loose.kind and (strict.C <= loose.C).all()  # judged more, never less
    assert loose.best == 0 and loose.C[0] == 1  # NAVSIM's 4 s fit smooths the tap away
    assert strict.C[0] == 0 and strict.kind[strict.best] == "idm"  # its first second does not
    assert strict.progress_m[strict.best] >= strict.progress_m[0]  # and gives up no progress


def test_the_plan_margin_keeps_the_learned_plan_unless_another_is_clearly_better():
    t = np.arange(1, 31) * 0.1  # the brake tap above: comfortable only by NAVSIM's 4 s fit
    x = np.cumsum(np.where(t <= 0.5, V - 2.0 * t, V - 1.0) * 0.1)
    tap = np.stack([x[4::5], np.zeros(6), np.zeros(6)], 1)
    occ, poses = history()
    strict = (1.0, 2.0)
    swapped = check_plan(occ, poses, tap, GRID, CheckConfig(comfort_prefixes_s=strict,
                                                            plan_margin=0.0))  # fmt: skip
    kept = check_plan(occ, poses, tap, GRID, CheckConfig(comfort_prefixes_s=strict,
                                                         plan_margin=0.25))  # fmt: skip
    c = kept.candidates
    assert swapped.candidates.best != 0 and c.best == 0  # comfort alone buys no replacement
    assert c.choice.max() - c.choice[0] > 0.1  # though another candidate scores higher
    np.testing.assert_array_equal(kept.trajectory, tap[:, :2].astype(np.float32))
    # A plan that leaves the road is replaced however large the margin.
    occ, poses = history(road_half_width=3.0)
    swerve = np.stack([V * t[4::5], 1.5 * t[4::5] ** 2, np.zeros(6)], 1)
    swerve[:, 2] = np.arctan2(np.gradient(swerve[:, 1]), np.gradient(swerve[:, 0]))
    c = check_plan(occ, poses, swerve, GRID, CheckConfig(plan_margin=2.0)).candidates
    assert c.DAC[0] == 0 and c.best != 0 and c.DAC[c.best] == 1


def test_a_pedestrian_leads_only_while_in_the_corridor():
    from renderworld.constants import EGO_CENTRE_OFFSET, EGO_LENGTH
    from renderworld.planning.candidates import leaders

    ped = (PED, lambda t: (20.0, -0.8 + 1.2 * t), (1, 1))  # in the lane now, walking out of it
    occ, poses = history([ped])
    scene = forecast_scene(occ, poses, GRID, 6)
    path = PlanPath(np.stack([np.arange(0, 40.0, 5.0), np.zeros(8)], 1), 60.0)
    (lead,) = leaders(scene, path, (0.0,), CheckConfig(), 3.0)
    gap_now, _ = lead.nearest(0, np.array([3.0]))
    gap_later, _ = lead.nearest(25, np.array([3.0]))  # 2.5 s on: it has crossed
    assert 15.0 < gap_now[0] < 20.0 and np.isinf(gap_later[0])
    # Held back by IDM wherever a leader is (cap_gap_s=None, the default), the plan brakes for
    # it, then drives on past where it would stop for a pedestrian standing there (2 m short of
    # it), speeding up again once the lane is clear.
    cfg = CheckConfig(cap_gap_s=None)
    x = check_plan(occ, poses, straight_plan(), GRID, cfg).candidates.waypoints[0, :, 0]
    step = np.diff(np.r_[0.0, x])
    assert x[-1] > 20.0 - 2.0 - (EGO_CENTRE_OFFSET + EGO_LENGTH / 2)
    assert step[-1] > step.min() + 0.3 and step.min() < 0.5 * V * DT
    # Held back only where it would come within s0 of a leader (cap_gap_s=0), the plan goes on
    # at its speed; the check finds it meets the pedestrian and brakes instead.
    c = check_plan(occ, poses, straight_plan(), GRID, CheckConfig(cap_gap_s=0.0)).candidates
    assert c.NC[0] == 0 and c.kind[c.best] == "brake" and c.NC[c.best] == c.TTC[c.best] == 1
    # A car standing in the lane is come near whatever the setting: the plan stops short of it.
    occ, poses = history([(CAR, lambda t: (25.0, -0.8), (2, 1))])
    ends = [check_plan(occ, poses, straight_plan(), GRID, CheckConfig(cap_gap_s=g))
            .candidates.waypoints[0, -1, 0] for g in (None, 0.0)]  # fmt: skip
    assert ends[0] == ends[1] < straight_plan()[-1, 0] - 10.0


def test_a_path_that_folds_back_is_driven_forwards():
    pts = np.array([[0.0, 0.0], [3.0, 0.0], [2.0, 0.1], [6.0, 0.2], [9.0, 0.2]])
    path = PlanPath(pts, 10.0)
    assert path.folded and (np.diff(path.xy[:, 0]) > 0).all()
    np.testing.assert_allclose(path.project(path.xy[:4]), path.s[:4], atol=1e-9)
    occ, poses = history()
    plan = straight_plan()
    plan[1, 0] = plan[0, 0] - 1.0  # the second waypoint behind the first
    c = check_plan(occ, poses, plan, GRID).candidates
    assert (np.diff(c.waypoints[:, :, 0], axis=1) >= -1e-6).all()


def test_a_standing_ego_is_not_at_fault_for_what_runs_into_it():
    car = (CAR, lambda t: (16.0 - 5.0 * t, -0.8), (2, 1))  # oncoming in the ego's lane
    occ, poses = history([car])
    poses[:, 0] = 0.0  # the ego stands
    for k in range(H):  # redraw the car in the standing ego's frames
        occ[k, :, :, :2] = np.where(occ[k, :, :, :2] == CAR, FREE_ID, occ[k, :, :, :2])
        ix, iy = _cell(16.0 - 5.0 * TIMES[k], -0.8)
        occ[k, ix : ix + 2, iy : iy + 1, :2] = CAR
    c = check_plan(occ, poses, straight_plan(speed=0.0), GRID).candidates
    standing = c.progress_m < 0.05
    assert standing.any() and (c.NC[standing] == 1).all() and c.NC[c.best] == 1


def test_a_change_of_plan_has_to_buy_something():
    occ, poses = history()
    slower = straight_plan(speed=8.0)[:, :2]  # the previous plan, carried on to now
    cfg = CheckConfig(change_cost=0.2, change_sideways=False)
    free = check_plan(occ, poses, straight_plan(), GRID)
    kept = check_plan(occ, poses, straight_plan(), GRID, cfg, previous=slower)
    dist = lambda w: np.hypot(*(w - slower).T).mean()  # noqa: E731
    assert dist(kept.trajectory) < dist(free.trajectory) - 0.5


def test_a_sideways_change_costs_and_a_change_of_speed_does_not():
    from renderworld.planning.check import plan_change

    previous = straight_plan()[:, :2]  # along +x at 10 m/s
    slower = straight_plan(speed=6.0)[:, :2]  # the same path, braking
    shifted = previous + [0.0, 1.0]  # one metre to the left
    wps = np.stack([previous, slower, shifted])
    np.testing.assert_allclose(plan_change(wps, previous, sideways=True), [0.0, 0.0, 1.0])
    full = plan_change(wps, previous, sideways=False)
    assert full[1] > 3.0 and full[2] == 1.0
    # Across a turning previous plan the normal turns with it: a shift along it costs nothing.
    ang = np.arange(1, 7) * 0.1
    arc = np.stack([20 * np.sin(ang), 20 * (1 - np.cos(ang))], -1)
    along = np.stack([20 * np.sin(ang + 0.02), 20 * (1 - np.cos(ang + 0.02))], -1)
    assert plan_change(along[None], arc, sideways=True)[0] < 0.02
    # In the check: braking behind a slower previous plan is not held to its speed.
    occ, poses = history()
    prev = straight_plan(8.0)[:, :2]
    cfg = CheckConfig(change_cost=0.2, change_sideways=True)
    kept = check_plan(occ, poses, straight_plan(), GRID, cfg, previous=prev)
    free = check_plan(occ, poses, straight_plan(), GRID, CheckConfig(change_cost=0.0),
                      previous=prev)  # fmt: skip
    np.testing.assert_array_equal(kept.trajectory, free.trajectory)
    held = check_plan(occ, poses, straight_plan(), GRID, replace(cfg, change_sideways=False),
                      previous=prev)  # fmt: skip
    assert not np.array_equal(held.trajectory, free.trajectory)  # the full distance holds it
    assert CheckConfig().change_sideways and CheckConfig().change_cost == 0.05  # the default


def _curve(state, radius, steps=6):
    """[steps, 2] waypoints 0.5 s apart on a left circle of ``radius`` m from ``state``."""
    ang = state.speed * DT * np.arange(1, steps + 1) / radius
    local = np.stack([radius * np.sin(ang), radius * (1 - np.cos(ang))], -1)
    c, s = np.cos(state.yaw), np.sin(state.yaw)
    return state.xy + local @ np.array([[c, s], [-s, c]])


def _accel_now(before, now):
    """The lateral acceleration now (m/s^2) from the ego states half a second apart, as the
    planner reads it from its last two history poses (:func:`lateral_accel_now`)."""
    from renderworld.planning.checked import lateral_accel_now

    c, s = np.cos(now.yaw), np.sin(now.yaw)
    back = (before.xy - now.xy) @ np.array([[c, -s], [s, c]])
    return lateral_accel_now(np.array([[*back, before.yaw - now.yaw], [0.0, 0.0, 0.0]]), V, DT)


def test_the_heading_rate_goes_on_where_a_new_plan_takes_over():
    from renderworld.planning.checked import continue_lateral_accel
    from renderworld.planning.kinematics import EgoState, KinematicLimits, track_plan

    lim = KinematicLimits()
    start = EgoState(0.0, 0.0, 0.0, V)
    driven, _ = track_plan(start, _curve(start, 40.0), lim, 5)  # half a second on a left curve
    now = driven[-1]
    rate_before = (driven[-1].yaw - driven[-2].yaw) / 0.1
    accel = _accel_now(start, now)
    assert accel == pytest.approx(V * rate_before, rel=0.05)  # v x yaw rate of the last step
    straight = np.stack([V * DT * np.arange(1, 7), np.zeros(6)], -1)  # the new plan: straight
    rates = {}
    continued = continue_lateral_accel(straight[None], accel)[0]
    for name, wp in (("raw", straight), ("continued", continued)):
        st, _ = track_plan(EgoState(0.0, 0.0, 0.0, now.speed), wp, lim, 5)
        rates[name] = st[0].yaw / 0.1
    assert abs(rates["raw"] - rate_before) > 0.1  # straight at once: the heading rate jumps
    assert abs(rates["continued"] - rate_before) < 0.25 * abs(rates["raw"] - rate_before)


@pytest.mark.parametrize("ease", [False, True])
def test_re_planning_from_a_curve_onto_a_straight_plan_weaves_unless_eased(ease):
    # The car leaves a left curve; every 0.5 s it re-plans the same straight plan, continued
    # from its lateral acceleration now, and drives its first segment. Moving the first
    # waypoint alone mirrors the start about the plan's own at the segment's end: the next plan
    # starts off by as much the other way, and the car weaves at two plans' period. Eased, each
    # segment ends at the plan's own (straight), so the weave dies.
    from renderworld.planning.checked import continue_lateral_accel
    from renderworld.planning.kinematics import EgoState, KinematicLimits, track_plan

    lim = KinematicLimits()
    prev = EgoState(0.0, 0.0, 0.0, V)
    driven, _ = track_plan(prev, _curve(prev, 40.0), lim, 5)
    straight = np.stack([V * DT * np.arange(1, 7), np.zeros(6)], -1)
    accels = []
    for _ in range(6):
        now = driven[-1]
        accel = _accel_now(prev, now)
        accels.append(accel)
        wp = continue_lateral_accel(straight[None], accel, DT, ease=ease)[0]
        c, s = np.cos(now.yaw), np.sin(now.yaw)
        to_scene = now.xy + wp @ np.array([[c, s], [-s, c]])
        prev, (driven, _) = now, track_plan(now, to_scene, lim, 5)
    accels = np.array(accels)
    assert abs(accels[0]) > 0.5  # m/s^2 on the curve
    if ease:
        assert np.abs(accels[1:]).max() < 0.1 * abs(accels[0])
    else:  # the sign flips at every plan and the size does not decay
        assert (np.sign(accels[1:]) == -np.sign(accels[:-1])).all()
        assert np.abs(accels[-1]) > 0.8 * abs(accels[0])


def test_a_slow_plan_wiggling_sideways_gives_a_straight_path():
    wiggle = np.array([[0.0, 0.0], [0.4, 0.05], [0.8, -0.05], [1.2, 0.05], [1.6, -0.05]])
    assert len(PlanPath(wiggle, 10.0).heading) == len(wiggle)  # every wiggle kept
    path = PlanPath(wiggle, 10.0, spacing_m=1.0)
    assert path.thinned and np.abs(np.diff(path.heading)).max() < 0.01
    occ, poses = history()
    plan = straight_plan(speed=0.4)  # 0.2 m a step, 5 cm to either side
    plan[:, 1] = 0.05 * (-1) ** np.arange(len(plan))

    def one_way(cfg):  # the offset-0 candidates move sideways one way only
        c = check_plan(occ, poses, plan, GRID, cfg).candidates
        step = np.diff(c.waypoints[c.offset_m == 0, :, 1], axis=1)
        return bool(((step <= 1e-9).all(1) | (step >= -1e-9).all(1)).all())

    assert one_way(CheckConfig()) and not one_way(CheckConfig(path_spacing_m=0.0))


def test_a_plan_turning_off_the_road_gives_way_to_the_steady_path():
    occ, poses = history(road_half_width=3.0)
    t = np.arange(1, 7) * DT
    swerve = np.stack([V * t, 1.5 * t * t, np.zeros(6)], 1)  # 13.5 m to the left at 3 s
    swerve[:, 2] = np.arctan2(np.gradient(swerve[:, 1]), np.gradient(swerve[:, 0]))
    out = check_plan(occ, poses, swerve, GRID)
    c = out.candidates
    assert c.kind[c.best].startswith("steady_") and c.DAC[c.best] == 1 and c.EP[c.best] > 0.95
    assert np.abs(out.trajectory[:, 1]).max() < 0.5  # on along the road, at speed
    assert out.trajectory[-1, 0] > 25.0
    alone = check_plan(occ, poses, swerve, GRID, CheckConfig(steady_path=False)).candidates
    assert not any(k.startswith("steady_") for k in alone.kind)
    assert alone.score.max() < c.score[c.best]


def test_the_steady_path_goes_on_at_the_turn_rate_now():
    from renderworld.planning.checked import steady_path_plan

    plan = straight_plan()  # top speed 10 m/s
    omega = 0.2  # rad/s, turning left
    ts = np.round(np.arange(-1.0, 1e-9, 0.1), 9)
    past = np.stack([V * ts, np.zeros_like(ts), omega * ts, np.full_like(ts, V)], 1)
    out = steady_path_plan(plan, past)
    radius = V / omega  # 50 m: curvature 0.02 /m
    np.testing.assert_allclose(np.hypot(out[:, 0], out[:, 1] - radius), radius, atol=1e-9)
    arc = radius * out[:, 2]
    np.testing.assert_allclose(arc, V * np.arange(1, 7) * DT, atol=1e-9)  # the plan's speed
    slow = past.copy()
    slow[:, 3] = 1.0  # below 2 m/s the heading rate is noise: straight ahead
    np.testing.assert_allclose(steady_path_plan(plan, slow)[:, 1:], 0.0, atol=1e-12)


def test_when_every_candidate_collides_the_hardest_brake_in_lane_wins():
    wall = (CAR, lambda t: (7.0, -8.0), (1, 10))  # a row of cars across the road, 7 m ahead
    occ, poses = history([wall], road_half_width=8.0)
    c = check_plan(occ, poses, straight_plan(), GRID).candidates
    assert (c.NC == 0).all()  # nothing stops in time
    assert c.offset_m[c.best] == 0.0 and c.kind[c.best].endswith("brake")
    assert c.progress_m[c.best] == c.progress_m[c.offset_m == 0.0].min()


def test_a_lead_car_met_by_an_oncoming_one_keeps_its_own_motion():
    # On the coarse grid the two cars' cells touch once they are side by side: one component.
    lead = (CAR, lambda t: (8.0 + 9.0 * t, -0.8), (3, 2))  # ahead in the ego's lane, 9 m/s
    oncoming = (CAR, lambda t: (10.0 - 7.0 * t, 1.6), (3, 2))  # the next lane, towards the ego
    occ, poses = history([lead, oncoming])
    from renderworld.world.tracks import track_movers

    merged = [tr for tr in track_movers(occ, poses, GRID, split_speed_mps=None) if tr.moving]
    assert len(merged) == 1  # one blob, matched to one of the two histories
    tracks = sorted((tr for tr in track_movers(occ, poses, GRID) if tr.moving),
                    key=lambda tr: tr.velocity[0])  # fmt: skip
    assert [float(tr.velocity[0]) for tr in tracks] == pytest.approx([-7.0, 9.0], abs=1.0)
    assert tracks[1].centroid[1] < 0.5 < tracks[0].centroid[1]  # each keeps its own lane's cells


def test_a_lead_car_met_by_an_oncoming_one_seen_once_before_keeps_its_history():
    # The oncoming car enters the grid half a second ago (one frame, no velocity to split by)
    # and touches the lead car now: the one component continues the lead car's track.
    lead = (CAR, lambda t: (28.0 + 12.0 * t, -0.8), (3, 2))  # 28 m ahead, 12 m/s
    oncoming = (CAR, lambda t: (28.0 - 12.0 * t if t > -0.75 else 1e4, 1.6), (3, 2))
    occ, poses = history([lead, oncoming])
    from renderworld.world.tracks import clear_track_cache, track_movers

    clear_track_cache()
    tracks = [tr for tr in track_movers(occ, poses, GRID) if tr.moving]
    assert len(tracks) == 1 and len(tracks[0].times) == H  # the whole history, the lead's
    assert float(tracks[0].velocity[0]) == pytest.approx(12.0, abs=1.5)


def test_however_uncomfortable_a_safe_plan_is_it_is_replaced_only_where_its_discomfort_counts():
    t = np.arange(1, 31) * 0.1  # 4 m/s^2 for 0.5 s from 10 m/s, then on at 8 m/s
    x = np.cumsum(np.where(t <= 0.5, V - 4.0 * t, V - 2.0) * 0.1)
    tap = np.stack([x[4::5], np.zeros(6), np.zeros(6)], 1)
    occ, poses = history()
    strict = (1.0, 2.0)  # judged on its first second, the tap breaks the jerk bound
    counted = check_plan(
        occ, poses, tap, GRID, CheckConfig(comfort_prefixes_s=strict, margin_counts_discomfort=True)
    )
    scored = check_plan(
        occ,
        poses,
        tap,
        GRID,
        CheckConfig(comfort_prefixes_s=strict, margin_counts_discomfort=False),
    )
    a, b = counted.candidates, scored.candidates
    assert a.C[0] == 0 and a.NC[0] == 1 and a.TTC[0] == 1 and a.DAC[0] == 1
    # Its discomfort cost puts it more than the plan margin behind a smooth candidate ...
    assert a.choice.max() - a.choice[0] > CheckConfig().plan_margin and a.best != 0
    # ... its score, which weighs comfort 2/12, does not: the learned plan is driven as planned.
    assert a.choice.max() - a.score[0] < CheckConfig().plan_margin and b.best == 0
    np.testing.assert_array_equal(scored.trajectory, tap[:, :2].astype(np.float32))


def test_progress_is_measured_along_the_plans_path():
    occ, poses = history(road_half_width=40.0)  # open ground: every candidate stays on it
    t = np.arange(1, 7) * DT
    yaw = 0.35 * t  # a left turn at 0.35 rad/s, 10 m/s
    turn = np.stack([np.cumsum(V * DT * np.cos(yaw - 0.175 * DT)),
                     np.cumsum(V * DT * np.sin(yaw - 0.175 * DT)), yaw], 1)  # fmt: skip
    along = check_plan(occ, poses, turn, GRID, CheckConfig(progress_along_plan=True)).candidates
    driven = check_plan(occ, poses, turn, GRID).candidates  # the distance driven (default)
    kinds = np.array(along.kind)
    straight = np.flatnonzero(kinds == "steady_idm")[0]  # straight on at the plan's speed
    assert driven.EP[straight] > 0.95 and along.EP[straight] < 0.9  # it leaves the turn
    assert along.EP[0] > 0.97 and driven.EP[0] > 0.97  # the plan itself makes full progress
    np.testing.assert_allclose(along.progress_m[0], driven.progress_m[0], atol=0.6)
    # A stalled plan (the ego stands; its plan creeps sideways, as a standing car's plan can)
    # keeps the distance driven: its path says nothing about where to go, and the steady path
    # straight ahead still counts.
    stand = np.zeros((H, 3))
    creep = np.stack([np.zeros(6), 0.05 * t, np.full(6, np.pi / 2)], 1)
    cfg = CheckConfig(progress_along_plan=True)
    c = check_plan(occ, stand, creep, GRID, cfg, cruise_speed=10.0).candidates
    ahead = np.flatnonzero(np.array(c.kind) == "steady_idm")
    assert c.progress_m[ahead].max() > 5.0 and c.EP[ahead].max() == 1.0


def test_the_side_margin_widens_the_box_sideways_only():
    from renderworld.constants import EGO_WIDTH

    # A parked car in the cells centred 2.4 m right of the path: the box (half its width and
    # the 0.2 m margin) passes it; 1.3 m more sideways reaches the cell centres.
    occ, poses = history([(CAR, lambda t: (20.0, -2.4), (3, 1))])
    plan = straight_plan()
    assert EGO_WIDTH / 2 + CheckConfig().box_margin_m < 2.4 < EGO_WIDTH / 2 + 0.2 + 1.3
    assert check_plan(occ, poses, plan, GRID).candidates.NC[0] == 1
    wide = CheckConfig(side_margin_m=1.3)
    assert check_plan(occ, poses, plan, GRID, wide).candidates.NC[0] == 0
    # Lengthwise nothing changes: a car 40 m ahead in the lane is met by neither.
    occ, poses = history([(CAR, lambda t: (50.0 + V * t, -0.8), (3, 2))])
    a = check_plan(occ, poses, plan, GRID).candidates
    b = check_plan(occ, poses, plan, GRID, CheckConfig(side_margin_m=0.4)).candidates
    assert a.NC[0] == b.NC[0] == 1 and a.TTC[0] == b.TTC[0] == 1


def test_soft_idm_runs_brake_no_harder_than_their_clip():
    occ, poses = history([(CAR, lambda t: (24.0, -0.8), (3, 2))], road_half_width=3.5)
    plan = straight_plan()
    plain = check_plan(occ, poses, plan, GRID).candidates
    assert "idm_soft" not in plain.kind
    c = check_plan(occ, poses, plan, GRID, CheckConfig(soft_min_accel=-4.0)).candidates
    soft = [i for i, k in enumerate(c.kind) if k == "idm_soft"]
    hard = [i for i, k in enumerate(c.kind) if k == "idm"]
    cfg = CheckConfig()
    assert len(soft) == len(hard) == len(cfg.offsets_m) * len(cfg.speed_fractions)

    def decel(i):  # the strongest braking between waypoints, m/s^2 (speeds from the waypoints)
        w = np.concatenate([[[0.0, 0.0]], c.waypoints[i]])
        v = np.r_[V, np.hypot(*np.diff(w, axis=0).T) / DT]
        return -np.diff(v).min() / DT

    straight = [i for i in soft + hard if c.offset_m[i] == 0.0]  # no sideways ramp in the speeds
    assert max(decel(i) for i in hard if i in straight) > 5.0  # IDM brakes hard behind the car
    assert max(decel(i) for i in soft if i in straight) < 4.0 + 1e-6  # its soft twin at most 4


def test_without_steady_for_comfort_a_safe_plan_is_not_left_for_the_steady_path():
    # A learned plan that swerves left at once on a free road: safe, but its lateral start
    # breaks comfort, so a comfortable steady-path run (straight on) replaces it by default;
    # with steady_for_comfort off no steady-path candidate is driven while the plan is safe.
    occ, poses = history()
    t = np.arange(1, 7) * DT
    plan = np.stack([V * t, 3.0 * np.minimum(t, 1.0) ** 2, np.zeros(6)], 1)
    base = check_plan(occ, poses, plan, GRID).candidates
    off = check_plan(occ, poses, plan, GRID, CheckConfig(steady_for_comfort=False)).candidates
    assert base.NC[0] * base.DAC[0] * base.TTC[0] == 1 and base.C[0] == 0
    assert base.kind[base.best].startswith("steady")
    assert not off.kind[off.best].startswith("steady")
