"""The IDM headway relaxed behind a vehicle that has just entered the corridor
(``CheckConfig.entrant_headway``, :mod:`renderworld.planning.relax`).

Hand-made scenes on the demo's coarse grid (the ego along +x at 10 m/s), as in ``test_idm``.
"""

import numpy as np

from renderworld.planning.candidates import CheckConfig, PlanPath, leaders
from renderworld.planning.checked import check_plan
from renderworld.planning.idm import FRONT, idm_arc
from renderworld.planning.relax import entrant_headways
from renderworld.planning.scene import forecast_scene

from .test_checked import CAR, GRID, PED, V, history, straight_plan

PATH = PlanPath(np.stack([np.arange(0, 40.0, 5.0), np.zeros(8)], 1), 60.0)
OFF = CheckConfig(entrant_headway=None)
ON = CheckConfig(entrant_headway=0.5, entrant_relax_s=2.0)


def scene_of(objects):
    occ, poses = history(objects)
    return forecast_scene(occ, poses, GRID, 6)


def run(scene, cfg):
    """(arc lengths [30] m, decelerations [30] m/s^2, leaders) of a 10 Hz IDM run at the ego's
    speed along PATH, with the config's headways."""
    hw = entrant_headways(scene, PATH, cfg)
    (lead,) = leaders(scene, PATH, (0.0,), cfg, 3.0, mover_headway=hw)
    s = idm_arc(V, [V], lead, cfg, 30, 0.1)[0]
    v = np.diff(np.r_[0.0, s]) / 0.1
    return s, -np.diff(np.r_[V, v]) / 0.1, lead


def cutting_in_now(v=V):
    """A car 8 m ahead of the front bumper at ``v`` m/s (the ego's speed), in the next lane until
    half a second ago (its cells 2.4-4.0 m right of the path) and in the ego's lane now."""
    return (CAR, lambda t: (FRONT + 8.0 + v * t, -3.2 if t < 0 else -1.6), (3, 2))


def test_a_car_cutting_in_is_followed_at_the_short_headway_and_not_braked_for_hard():
    scene = scene_of([cutting_in_now()])
    # Last seen outside 0.5 s ago: a quarter of the way back to the full 1.5 s.
    np.testing.assert_allclose(entrant_headways(scene, PATH, ON), [0.75])
    assert entrant_headways(scene, PATH, OFF) is None
    s_off, decel_off, lead = run(scene, OFF)
    s_on, decel_on, _ = run(scene, ON)
    # Full headway: IDM's emergency braking; relaxed: firm, within NAVSIM's bound (4.05).
    assert decel_off.max() > 6.0 and decel_on.max() < 4.05
    # Still behind it at the end, by more than the standstill gap.
    gap_end = lead.nearest(29, np.array([s_on[-1] + FRONT]), V)[0][0]
    assert s_on[-1] > s_off[-1] and gap_end > ON.s0


def test_a_car_about_to_cut_in_gets_the_short_headway():
    # Still in the next lane now, drifting towards the ego's (its forecast takes it in).
    car = (CAR, lambda t: (FRONT + 10.0 + 8.0 * t, -3.2 + 0.8 * t), (3, 2))
    np.testing.assert_allclose(entrant_headways(scene_of([car]), PATH, ON), [0.5])


def test_the_headway_relaxes_back_over_the_seconds_after_the_entry():
    # In the next lane until 1 s ago, in the ego's lane since: halfway back to 1.5 s.
    car = (CAR, lambda t: (FRONT + 8.0 + 8.0 * t, -3.2 if t < -0.75 else -1.6), (3, 2))
    hw = entrant_headways(scene_of([car]), PATH, ON)[0]
    np.testing.assert_allclose(hw, 0.5 + (1.5 - 0.5) * 1.0 / 2.0)
    # Entered more than entrant_relax_s ago (or never outside): the full headway.
    assert entrant_headways(scene_of([car]), PATH, CheckConfig(entrant_relax_s=1.0))[0] == 1.5


def test_a_lead_car_an_oncoming_car_and_a_pedestrian_keep_the_full_headway():
    lead_car = (CAR, lambda t: (FRONT + 12.0 + 6.0 * t, -0.8), (3, 2))
    oncoming = (CAR, lambda t: (FRONT + 30.0 - 8.0 * t, -3.2 if t < 0 else -1.6), (3, 2))
    walker = (PED, lambda t: (FRONT + 10.0, -3.2 if t < 0 else -1.6), (1, 1))
    for obj in (lead_car, oncoming, walker):
        scene = scene_of([obj])
        np.testing.assert_array_equal(entrant_headways(scene, PATH, ON), [ON.headway])
    # Behind the lead car the runs are the same, bit for bit.
    scene = scene_of([lead_car])
    np.testing.assert_array_equal(run(scene, ON)[0], run(scene, OFF)[0])


def test_the_checked_plan_is_held_back_less_behind_a_car_cutting_in():
    occ, poses = history([cutting_in_now()])
    plan = straight_plan()
    off = check_plan(occ, poses, plan, GRID, OFF).candidates
    on = check_plan(occ, poses, plan, GRID, ON).candidates
    # The learned plan's own candidate (held back by IDM behind the car) goes farther in 1 s.
    assert on.waypoints[0, 1, 0] > off.waypoints[0, 1, 0] + 0.2
    assert CheckConfig().entrant_headway == 0.5  # the planner's default relaxes
