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
