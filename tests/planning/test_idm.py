"""IDM behind the forecast's leaders: anticipated leaders (``CheckConfig.anticipate_s``).

Hand-made scenes on the demo's coarse grid (the ego along +x at 10 m/s; the forecast's movers
at constant velocity), as in ``test_checked``.
"""

from dataclasses import replace

import numpy as np
import pytest

from renderworld.planning.candidates import CheckConfig, PlanPath, leaders
from renderworld.planning.checked import check_plan
from renderworld.planning.idm import FRONT, idm_arc
from renderworld.planning.scene import forecast_scene

from .test_checked import CAR, GRID, PED, V, history, straight_plan

PATH = PlanPath(np.stack([np.arange(0, 40.0, 5.0), np.zeros(8)], 1), 60.0)


def idm_run(scene, cfg):
    """(arc lengths [30] m, decelerations [30] m/s^2) of a 10 Hz IDM run at the ego's speed along
    PATH behind ``scene``'s leaders, and those leaders."""
    (lead,) = leaders(scene, PATH, (0.0,), cfg, 3.0)
    s = idm_arc(V, [V], lead, cfg, 30, 0.1)[0]
    v = np.diff(np.r_[0.0, s]) / 0.1
    return s, -np.diff(np.r_[V, v]) / 0.1, lead


def cut_in(lateral=1.0):
    """A car in the right-hand lane 14 m ahead at the ego's speed, drifting left into its lane
    at ``lateral`` m/s (its cells start 3.2 m right of the path)."""
    return (CAR, lambda t: (14.0 + V * t, -4.0 + lateral * t), (3, 1))


def test_a_car_cutting_in_leads_from_when_its_cut_in_is_foreseen():
    occ, poses = history([cut_in()])
    scene = forecast_scene(occ, poses, GRID, 6)
    (now,) = leaders(scene, PATH, (0.0,), CheckConfig(), 3.0)
    (early,) = leaders(scene, PATH, (0.0,), CheckConfig(anticipate_s=3.0), 3.0)
    front = np.array([FRONT])
    gap_now, _ = now.nearest(0, front, V)
    gap_early, speed = early.nearest(0, front, V)
    assert np.isinf(gap_now[0])  # not in the corridor yet
    # Led by from now on, where it is along the path now (its rear cell's centre), at its speed
    # along the path.
    rear = (
        GRID.range_min[0]
        + (np.floor((14.0 - GRID.range_min[0]) / GRID.voxel_size[0]) + 0.5) * GRID.voxel_size[0]
    )
    assert abs(gap_early[0] - (rear - FRONT)) < 0.5 and abs(speed[0] - V) < 0.5
    # Once in the corridor it leads either way, at the same gap.
    i = int(np.flatnonzero(np.isfinite(now.arc).any(1))[0])
    assert 0 < i <= 30
    g1, _ = now.nearest(i, front, V)
    g2, _ = early.nearest(i, front, V)
    np.testing.assert_allclose(g1, g2)


def test_an_idm_run_behind_a_foreseen_cut_in_brakes_earlier_and_gentler():
    # A slower car (7 m/s) 20 m ahead cutting in: followed only once it is in the lane, IDM
    # brakes beyond NAVSIM's comfort bound (-4.05 m/s^2); followed from when it is foreseen,
    # within it, from the start.
    slow = (CAR, lambda t: (20.0 + 7.0 * t, -4.0 + 1.5 * t), (3, 1))
    occ, poses = history([slow])
    scene = forecast_scene(occ, poses, GRID, 6)
    first, hardest = {}, {}
    for ahead in (0.0, 3.0):
        _, decel, _ = idm_run(scene, CheckConfig(anticipate_s=ahead))
        first[ahead] = int(np.argmax(decel > 0.5))
        hardest[ahead] = decel.max()
    assert first[3.0] == 0 and first[0.0] >= 10  # brakes now, not a second or more later
    assert hardest[0.0] > 5.0 and hardest[3.0] < 4.0


def test_a_pedestrian_the_ego_will_have_passed_does_not_lead():
    # 10 m ahead, 5 m to the right, walking towards the lane: inside the corridor in about 3 s.
    ped = (PED, lambda t: (10.0, -5.6 + 1.5 * t), (1, 1))
    occ, poses = history([ped], road_half_width=8.0)
    scene = forecast_scene(occ, poses, GRID, 6)
    (lead,) = leaders(scene, PATH, (0.0,), CheckConfig(anticipate_s=3.0), 3.0)
    front = np.array([FRONT])
    gap_fast, _ = lead.nearest(0, front, V)  # at 10 m/s the ego is long past by then
    gap_slow, _ = lead.nearest(0, front, 0.5)  # at a crawl it is not
    assert np.isinf(gap_fast[0]) and np.isfinite(gap_slow[0])
    assert gap_slow[0] < 10.0 - FRONT + 1.0 + 1e-9


def test_the_plan_is_held_back_for_a_cut_in_from_when_it_is_foreseen():
    occ, poses = history([cut_in()])
    plan = straight_plan()
    off = check_plan(occ, poses, plan, GRID, CheckConfig(anticipate_s=0.0)).candidates
    on = check_plan(occ, poses, plan, GRID, CheckConfig(anticipate_s=3.0)).candidates
    # The plan's own candidate, held back by IDM behind the car from now on, is nearer at 1 s.
    assert on.waypoints[0, 1, 0] < off.waypoints[0, 1, 0] - 0.2
    assert CheckConfig().anticipate_s > 0  # the planner's default anticipates


def test_the_constant_acceleration_heuristic_is_the_kinematic_need():
    from renderworld.planning.idm import cah_accel

    # Closing at 4 m/s on a leader holding its speed 8 m ahead: 4^2 / (2 x 8) = 1 m/s^2.
    np.testing.assert_allclose(cah_accel(np.r_[10.0], np.r_[6.0], np.r_[0.0], np.r_[8.0], 1.5),
                               [-1.0])  # fmt: skip
    # Not closing: no braking needed.
    assert cah_accel(np.r_[6.0], np.r_[10.0], np.r_[0.0], np.r_[8.0], 1.5)[0] == 0.0
    # A leader braking at 4 m/s^2 from the same speed, 10 m ahead: brake as hard as it does.
    np.testing.assert_allclose(cah_accel(np.r_[10.0], np.r_[10.0], np.r_[-4.0], np.r_[10.0],
                                         1.5), [-4.0 * 100 / (100 + 80)])  # fmt: skip


def test_the_acc_model_brakes_firmly_not_hard_for_a_close_car_cutting_in_not_much_slower():
    # A car at 8 m/s cutting in 8 m ahead of the ego's front bumper (at 10 m/s), in the lane
    # from the start: IDM over-reacts (its desired gap is 22 m: an emergency stop at the clip);
    # the ACC model brakes firmly, within NAVSIM's comfort bound, and still stays behind it.
    car = (CAR, lambda t: (FRONT + 8.0 + 8.0 * t, -0.8), (3, 2))
    occ, poses = history([car])
    scene = forecast_scene(occ, poses, GRID, 6)
    hardest, end = {}, {}
    for cool in (0.0, 0.99):
        s, decel, lead = idm_run(scene, CheckConfig(acc_coolness=cool))
        hardest[cool] = decel.max()
        end[cool] = lead.nearest(29, np.array([s[-1] + FRONT]))[0][0]
    assert hardest[0.0] > 7.9 and hardest[0.99] < 4.05
    assert end[0.99] > 2.0  # the standstill gap s0 is kept


def test_idm_plus_does_not_brake_at_its_speed_behind_a_car_pulling_away():
    # A car at 13 m/s 14 m ahead of the front bumper, in the lane: at its desired speed (10 m/s)
    # IDM brakes for it all the same (its free-road term is 0, the interaction term is not);
    # IDM+ keeps its speed. Behind a slower car (7 m/s) both brake.
    hardest = {}
    for v_lead in (13.0, 7.0):
        car = (CAR, lambda t, v=v_lead: (FRONT + 14.0 + v * t, -0.8), (3, 2))
        occ, poses = history([car])
        scene = forecast_scene(occ, poses, GRID, 6)
        for plus in (False, True):
            _, decel, _ = idm_run(scene, CheckConfig(idm_plus=plus))
            hardest[v_lead, plus] = decel.max()
    assert hardest[13.0, False] > 0.3 and abs(hardest[13.0, True]) < 1e-6, hardest
    assert hardest[7.0, False] > 1.0 and hardest[7.0, True] > 1.0, hardest


def test_cap_coolness_softens_the_plans_hold_back_only():
    # The car at 8 m/s cutting in 8 m ahead (above): the learned plan held back by plain IDM
    # brakes beyond NAVSIM's comfort bound in its first half second; held back by the ACC model
    # it brakes within it, and the IDM candidates beside it are the same either way (the
    # leader-stop cap off: the quantised track of this steady car reads as braking hard).
    car = (CAR, lambda t: (FRONT + 8.0 + 8.0 * t, -0.8), (3, 2))
    occ, poses = history([car])
    plan = straight_plan()
    cfg = CheckConfig(steady_path=False, continuous_start=False, leader_stop_cap=False)
    plain = check_plan(occ, poses, plan, GRID, cfg).candidates
    cool = check_plan(occ, poses, plan, GRID, replace(cfg, cap_coolness=0.99)).candidates

    def first_decel(wp):  # m/s^2, constant over the first 0.5 s, from the first waypoint
        return 2.0 * (V * 0.5 - wp[0, 0]) / 0.5**2

    assert first_decel(plain.waypoints[0]) > 6.0 and first_decel(cool.waypoints[0]) < 4.05
    idm = [i for i, k in enumerate(plain.kind) if k == "idm"]
    np.testing.assert_array_equal(plain.waypoints[idm], cool.waypoints[idm])


@pytest.mark.parametrize(
    "knobs",
    [
        {},
        {"anticipate_s": 0.0},
        {"acc_coolness": 0.99},
        {"idm_plus": True},
        {"entrant_headway": None},
    ],
)
def test_the_batched_idm_runs_equal_their_reference_twin(knobs):
    # Three lateral offsets' leaders in one scene (a car cutting in, a slow lead car, a
    # pedestrian), each with its own targets: the batched loop gives the runs one by one.
    from renderworld.planning.idm import idm_arcs
    from renderworld.planning.relax import entrant_headways

    lead_car = (CAR, lambda t: (30.0 + 6.0 * t, -0.8), (3, 2))
    ped = (PED, lambda t: (18.0, 4.0 - 1.2 * t), (1, 1))
    occ, poses = history([cut_in(), lead_car, ped], road_half_width=8.0)
    scene = forecast_scene(occ, poses, GRID, 6)
    cfg = replace(CheckConfig(), **knobs)
    hw = entrant_headways(scene, PATH, cfg)  # the car cutting in: a shorter headway
    assert hw is None if cfg.entrant_headway is None else hw.min() < cfg.headway
    leads = leaders(scene, PATH, (0.0, 2.0, -2.0), cfg, 3.0, mover_headway=hw)
    targets = [[V, 7.5, 5.0], [V], [12.0, 2.0]]
    batched = idm_arcs(V, targets, leads, cfg, 6, 0.5)
    for t, lead, got in zip(targets, leads, batched):
        np.testing.assert_array_equal(got, idm_arc(V, t, lead, cfg, 6, 0.5))
    # The leaders matter: shifted 2 m left, towards the pedestrian, the run at the ego's speed
    # ends far short of the 30 m of a free road.
    assert batched[1][0, -1] < 20.0
    assert len(idm_arcs(V, [[], []], leads[:2], cfg, 6, 0.5)[0]) == 0
    with pytest.raises(ValueError, match="leads"):
        short = leaders(scene, PATH, (0.0,), cfg, 2.0)
        idm_arcs(V, [[V], [V]], [leads[0], short[0]], cfg, 6, 0.5)
