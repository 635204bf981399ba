"""``CheckConfig.lead_brake_decel``: the learned plan stays behind the leader's worst case (a
brake to a stop from now); ``CheckConfig.leader_stop_cap``: every candidate stays behind a leader
that brakes hard. Hand-made scenes as in ``test_checked`` (the ego along +x at 10 m/s)."""

import numpy as np

from renderworld.planning.candidates import CheckConfig, make_candidates
from renderworld.planning.checked import past_states
from renderworld.planning.idm import FRONT
from renderworld.planning.scene import forecast_scene

from .test_checked import CAR, DT, GRID, V, history, straight_plan


def _plan_arcs(lead_x, lead_v, cfg):
    """The plan candidate's arc lengths [6] (metres along +x) behind a car whose rear is at
    ``lead_x`` now, driving at ``lead_v`` (m/s)."""
    car = (CAR, lambda t: (lead_x + lead_v * t, -1.6), (3, 2))
    occ, poses = history([car], road_half_width=6.0)
    scene = forecast_scene(occ, poses, GRID, 6)
    plan = straight_plan()
    speed = float(past_states(poses, DT)[-1, 3])
    c = make_candidates(plan[:, :2], plan[:, 2], speed, scene, cfg, DT)
    assert c.kind[0] == "plan" and c.offset_m[0] == 0.0
    return c.waypoints[0, :, 0]


def test_the_plan_stays_behind_where_a_braking_leader_would_stop():
    base = _plan_arcs(15.0, V, CheckConfig())
    env = _plan_arcs(15.0, V, CheckConfig(lead_brake_decel=4.0))
    # A car 15 m ahead at the plan's speed: IDM lets the plan drive on (25.7 of its 30 m).
    assert base[-1] > 25.0
    # Braking at 4 m/s^2 from 10 m/s it would stop 12.5 m on: the plan ends s0 behind that
    # (the car's rear within a 1.6 m cell of 15 m), 3 m short of where it went.
    stop = 15.0 + V**2 / (2 * 4.0) - CheckConfig().s0 - FRONT
    assert env[-1] <= stop + 0.8 + 1e-6 and env[-1] < base[-1] - 2.5
    assert (np.diff(np.concatenate([[0.0], env])) >= -1e-9).all()  # never backwards
    np.testing.assert_array_equal(env[:5], base[:5])  # the first 2.5 s unchanged here


def test_the_envelope_never_asks_for_more_than_a_6_m_s2_stop():
    base = _plan_arcs(9.0, 0.0, CheckConfig())  # a car standing 9 m ahead
    env = _plan_arcs(9.0, 0.0, CheckConfig(lead_brake_decel=4.0))
    t = np.arange(1, 7) * DT
    floor = np.where(t < V / 6.0, V * t - 3.0 * t * t, V * V / 12.0)
    assert (env >= np.minimum(floor, base) - 1e-6).all() and (env <= base + 1e-9).all()


def test_with_the_leader_stop_cap_no_candidate_runs_past_a_braking_leaders_stop():
    from renderworld.planning.checked import cap_behind_leader, check_plan
    from renderworld.world.pose_retime import leader_stop_room, stop_profile

    # A car in the lane 18 m ahead now, braking at 4 m/s^2 (6 m/s now, 14 m/s 2 s ago).
    car = (CAR, lambda t: (18.0 + 6.0 * t - 2.0 * t * t, -0.8), (3, 2))
    occ, poses = history([car], road_half_width=6.0)
    room = leader_stop_room(forecast_scene(occ, poses, GRID, 6).tracks, poses, GRID)
    assert room is not None and 10.0 < room < 25.0
    plan = straight_plan()
    limit = stop_profile(np.full(6, 1e9), V, room, DT)  # the stop from 10 m/s at the room

    def arcs(wp):
        pts = np.concatenate([np.zeros((len(wp), 1, 2)), wp], axis=1)
        return np.cumsum(np.linalg.norm(np.diff(pts, axis=1), axis=-1), axis=1)

    free = check_plan(occ, poses, plan, GRID, CheckConfig(leader_stop_cap=False))
    capped = check_plan(occ, poses, plan, GRID, CheckConfig())  # the default
    assert (arcs(free.candidates.waypoints) > limit + 0.5).any()  # some candidate would run past
    assert (arcs(capped.candidates.waypoints) <= limit + 1e-6).all()
    assert np.all(np.diff(arcs(capped.candidates.waypoints), axis=1) >= -1e-9)
    # No leader coming to a stop: the candidates come back as they went in.
    occ0, poses0 = history([], road_half_width=6.0)
    wp = np.stack([plan[:, :2], plan[:, :2] * 0.5])
    tracks0 = forecast_scene(occ0, poses0, GRID, 6).tracks
    assert cap_behind_leader(wp, tracks0, poses0, GRID, DT) is wp


def _lane_change_past_a_slower_car():
    """History and plan: a car 7 m ahead in the ego's lane at 7 m/s; the plan changes lane to
    the left over 3 s."""
    car = (CAR, lambda t: (7.0 + 7.0 * t, -1.6), (3, 2))
    occ, poses = history([car], road_half_width=6.0)
    t = np.arange(1, 7) * DT
    u = t / 3.0
    plan = np.stack([V * t, 3.5 * u * u * (3 - 2 * u), np.zeros(6)], 1)
    plan[:, 2] = np.arctan2(np.gradient(plan[:, 1]), np.gradient(plan[:, 0]))
    return occ, poses, plan


def test_hold_if_unsafe_drives_a_lane_change_past_a_slower_car_as_learned():
    from renderworld.planning.checked import check_plan

    occ, poses, plan = _lane_change_past_a_slower_car()
    held = check_plan(occ, poses, plan, GRID, CheckConfig())
    kept = check_plan(occ, poses, plan, GRID, CheckConfig(hold_if_unsafe=True))
    # Held back behind the car its path leaves, the plan is replaced by another candidate.
    assert np.abs(held.trajectory - plan[:, :2]).max() > 2.0
    # As learned it meets nothing in the forecast and keeps time to collision: it is driven.
    c = kept.candidates
    assert c.best == 0 and c.NC[0] == 1 and c.TTC[0] == 1
    np.testing.assert_allclose(kept.trajectory[1:], plan[1:, :2], atol=1e-5)


def test_hold_if_unsafe_still_holds_a_plan_that_would_hit_a_standing_car():
    from renderworld.planning.checked import check_plan

    car = (CAR, lambda t: (28.0, -2.4), (3, 3))  # blocks the road 28 m ahead
    occ, poses = history([car], road_half_width=3.5)
    plan = straight_plan()
    out = check_plan(occ, poses, plan, GRID, CheckConfig(hold_if_unsafe=True))
    c = out.candidates
    assert c.waypoints[0, -1, 0] < plan[-1, 0] - 5.0  # its own candidate held back behind it
    assert c.NC[c.best] == 1


def test_hold_behind_movers_still_holds_the_plan_behind_a_moving_car():
    from renderworld.planning.checked import check_plan
    from renderworld.planning.scene import forecast_scene
    from renderworld.planning.standing import moving_points

    occ, poses, plan = _lane_change_past_a_slower_car()
    assert moving_points(forecast_scene(occ, poses, GRID, 6)).any()
    held = check_plan(occ, poses, plan, GRID, CheckConfig())
    movers = check_plan(occ, poses, plan, GRID,
                        CheckConfig(hold_if_unsafe=True, hold_behind_movers=True))  # fmt: skip
    # The car moves: its forecast may be wrong, so the headway behind it stays.
    np.testing.assert_allclose(movers.candidates.waypoints[0], held.candidates.waypoints[0],
                               atol=1e-6)  # fmt: skip
    np.testing.assert_allclose(movers.trajectory, held.trajectory, atol=1e-6)
    # A parked car stands: none of its points is a moving one.
    parked = (CAR, lambda t: (28.0, -2.4), (3, 3))
    occ2, poses2 = history([parked], road_half_width=3.5)
    assert not moving_points(forecast_scene(occ2, poses2, GRID, 6)).any()
