"""The IDM headway behind what stands (``CheckConfig.standing_headway``,
:mod:`renderworld.planning.standing`).

Hand-made scenes on the demo's coarse grid (the ego along +x at 10 m/s), as in ``test_relax``.
"""

from dataclasses import replace

import numpy as np

from renderworld.constants import OCC3D_CLASSES
from renderworld.planning.candidates import CheckConfig, PlanPath, leaders
from renderworld.planning.checked import check_plan
from renderworld.planning.idm import FRONT, idm_arc
from renderworld.planning.relax import entrant_headways
from renderworld.planning.scene import forecast_scene
from renderworld.planning.standing import mover_travel, standing_headways

from .test_checked import CAR, GRID, PED, V, history, straight_plan

PATH = PlanPath(np.stack([np.arange(0, 40.0, 5.0), np.zeros(8)], 1), 60.0)
OFF = CheckConfig(standing_headway=None)
ON = CheckConfig(standing_headway=0.5)
WALL = OCC3D_CLASSES.index("manmade")


def scene_of(objects):
    occ, poses = history(objects)
    return forecast_scene(occ, poses, GRID, 6)


def run(scene, cfg):
    """(arc lengths [30] m, decelerations [30] m/s^2, leaders) of a 10 Hz IDM run at the ego's
    speed along PATH, with the config's headways."""
    hw = standing_headways(scene, PATH, cfg, entrant_headways(scene, PATH, cfg))
    (lead,) = leaders(scene, PATH, (0.0,), cfg, 3.0, mover_headway=hw)
    s = idm_arc(V, [V], lead, cfg, 30, 0.1)[0]
    v = np.diff(np.r_[0.0, s]) / 0.1
    return s, -np.diff(np.r_[V, v]) / 0.1, lead


def parked(ahead=25.0):
    """A car standing in the ego's lane, its rear ``ahead`` metres before the front bumper."""
    return (CAR, lambda t: (FRONT + ahead, -0.8), (3, 2))


def test_a_parked_car_is_approached_at_the_short_headway_and_still_stopped_behind():
    scene = scene_of([parked()])
    assert mover_travel(scene)[0] < 1.0
    np.testing.assert_allclose(standing_headways(scene, PATH, ON), [0.5])
    assert standing_headways(scene, PATH, OFF) is None
    s_off, decel_off, lead = run(scene, OFF)
    s_on, decel_on, _ = run(scene, ON)
    # The full headway brakes from the start; the short one later and less hard at first.
    assert s_on[9] > s_off[9] + 0.5 and decel_on[:5].max() < decel_off[:5].max()
    # Still behind it at the end, by more than the standstill gap, and within NAVSIM's bound.
    gap_end = lead.nearest(29, np.array([s_on[-1] + FRONT]), 0.0)[0][0]
    assert gap_end > ON.s0 and decel_on.max() < 4.05


def test_static_scenery_and_a_car_that_has_just_stopped_keep_the_full_headway():
    wall = scene_of([(WALL, lambda t: (FRONT + 25.0, -0.8), (3, 2))])
    assert len(wall.displacements) == 0
    np.testing.assert_array_equal(run(wall, ON)[0], run(wall, OFF)[0])
    # A lead car braking at 3 m/s^2 to a stop 25 m ahead of the front bumper now: the tracker
    # saw it move; even where the forecast keeps it still, it keeps the full headway.
    stopped = scene_of([(CAR, lambda t: (FRONT + 25.0 - 1.5 * min(t, 0.0) ** 2, -0.8), (3, 2))])
    assert stopped.tracks[0].moving
    still = replace(stopped, displacements=np.zeros_like(stopped.displacements))
    assert mover_travel(still)[0] == 0.0
    np.testing.assert_array_equal(standing_headways(still, PATH, ON), [ON.headway])


def test_a_moving_lead_car_and_a_standing_pedestrian_keep_the_full_headway():
    lead_car = (CAR, lambda t: (FRONT + 12.0 + 6.0 * t, -0.8), (3, 2))
    walker = (PED, lambda t: (FRONT + 15.0, -0.8), (1, 1))
    for obj in (lead_car, walker):
        scene = scene_of([obj])
        np.testing.assert_array_equal(standing_headways(scene, PATH, ON), [ON.headway])
        np.testing.assert_array_equal(run(scene, ON)[0], run(scene, OFF)[0])
    # An entrant's shorter headway is kept where the mover moves.
    kept = standing_headways(scene_of([lead_car]), PATH, ON, np.array([0.7]))
    np.testing.assert_array_equal(kept, [0.7])


def test_the_checked_plan_is_held_back_less_behind_a_parked_car():
    occ, poses = history([parked(28.0)])
    plan = straight_plan()
    off = check_plan(occ, poses, plan, GRID, OFF).candidates
    on = check_plan(occ, poses, plan, GRID, ON).candidates
    # The learned plan's own candidate (held back by IDM behind the car) goes farther in 1 s.
    assert on.waypoints[0, 1, 0] > off.waypoints[0, 1, 0] + 0.2
    assert CheckConfig().standing_headway == 0.5  # the planner's default


def test_a_car_parked_where_the_path_has_left_the_road_keeps_the_full_headway():
    # A path bending off a 7 m road (as the straight extension beyond a turning plan's end
    # does) meets a car parked on the far side of the kerb: it is not on the road ahead.
    occ, poses = history([(CAR, lambda t: (FRONT + 25.0, -5.6), (3, 2))], road_half_width=3.5)
    scene = forecast_scene(occ, poses, GRID, 6)
    xs = np.arange(0, 40.0, 5.0)
    bend = PlanPath(np.stack([xs, -0.2 * xs], 1), 60.0)
    assert mover_travel(scene)[0] < 1.0 and not scene.tracks[0].moving
    np.testing.assert_array_equal(standing_headways(scene, bend, ON), [ON.headway])
    # The same car on a path along the road (the road widened to hold it) gets the short one.
    occ, poses = history([(CAR, lambda t: (FRONT + 25.0, -5.6), (3, 2))], road_half_width=8.0)
    wide = forecast_scene(occ, poses, GRID, 6)
    np.testing.assert_allclose(standing_headways(wide, bend, ON), [0.5])


def test_a_slow_ego_keeps_the_full_headway_with_a_least_speed():
    scene = scene_of([parked()])
    slow = CheckConfig(standing_headway=0.5, standing_min_speed=3.0)
    np.testing.assert_allclose(standing_headways(scene, PATH, slow, speed=10.0), [0.5])
    # Creeping at 2 m/s behind a car that may drive off: the full headway, or the entrant's.
    assert standing_headways(scene, PATH, slow, speed=2.0) is None
    kept = standing_headways(scene, PATH, slow, np.array([0.7]), speed=2.0)
    np.testing.assert_array_equal(kept, [0.7])
