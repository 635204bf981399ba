"""Passing a parked road user (``CheckConfig.pass_parked``): hand-made scenes as in
``test_checked`` (the demo's coarse grid, 1.6 m voxels; the ego along +x at 10 m/s)."""

import numpy as np

from renderworld.constants import EGO_WIDTH
from renderworld.planning.candidates import CheckConfig, PlanPath
from renderworld.planning.checked import check_plan
from renderworld.planning.idm import FRONT
from renderworld.planning.passing import parked_blocker, pass_candidates
from renderworld.planning.scene import forecast_scene

from .test_checked import CAR, GRID, PED, V, history, straight_plan

ON = CheckConfig(pass_parked=True, standing_headway=None)  # the full headway: held back, not braked
OFF = CheckConfig(pass_parked=False, standing_headway=None)
PATH = PlanPath(np.concatenate([np.zeros((1, 2)), straight_plan()[:, :2]]), 60.0)


def parked(x=25.0, y=-1.6, cells=(3, 2)):
    """A car standing with its rear at world x (metres ahead of the ego now), cells from y."""
    return (CAR, lambda t: (x, y), cells)


def test_a_parked_car_in_the_lane_is_found_with_the_free_offsets_on_both_sides():
    occ, poses = history([parked()], road_half_width=6.0)
    scene = forecast_scene(occ, poses, GRID, 6)
    b = parked_blocker(scene, PATH, V, ON)
    # Its cells' centres lie at y = -2.4 and -0.8: the shifted ego box must clear both by the
    # clearance, on the 0.25 m steps tried.
    clear = EGO_WIDTH / 2 + ON.pass_clearance_m
    assert b is not None and abs(b.gap_m - (24.8 - FRONT)) < 1e-6
    assert b.left - 0.25 < -0.8 + clear <= b.left
    assert b.right + 0.25 > -2.4 - clear >= b.right


def test_moving_cars_pedestrians_and_cars_beside_the_lane_are_not_passed():
    moving = (CAR, lambda t: (25.0 + 5.0 * t, -1.6), (3, 2))
    beside = parked(y=-6.4)  # cells from -6.4 to -3.2: outside the corridor
    ped = (PED, lambda t: (20.0, -0.8), (1, 1))
    for obj in (moving, beside, ped):
        occ, poses = history([obj], road_half_width=8.0)
        scene = forecast_scene(occ, poses, GRID, 6)
        assert parked_blocker(scene, PATH, V, ON) is None
        wps, offs, _ = pass_candidates(PATH, V, V, scene, ON, 6, 0.5)
        assert wps.shape == (0, 6, 2) and len(offs) == 0
    occ, poses = history([parked()], road_half_width=6.0)  # off: no pass proposed
    scene = forecast_scene(occ, poses, GRID, 6)
    assert len(pass_candidates(PATH, V, V, scene, OFF, 6, 0.5)[1]) == 0


def test_a_parked_car_is_passed_instead_of_waited_behind():
    occ, poses = history([parked()], road_half_width=6.0)
    plan = straight_plan()
    off = check_plan(occ, poses, plan, GRID, OFF).candidates
    on = check_plan(occ, poses, plan, GRID, ON).candidates
    # Without passing, the plan is held back behind the car (IDM): 16.6 of its 30 m.
    assert off.kind[off.best] == "plan" and off.progress_m[off.best] < 20.0
    # With it, a pass to the left at the plan's speed: no contact, on the road, comfortable,
    # beside the car when level with it, and its full progress.
    b = on.best
    assert on.kind[b] == "pass" and on.offset_m[b] > 0 and on.speed[b] == V
    assert on.NC[b] == on.DAC[b] == on.C[b] == on.TTC[b] == 1.0 and on.EP[b] == 1.0
    level = np.abs(on.waypoints[b, :, 0] - 26.0) < 6.0
    assert level.any() and (on.waypoints[b, level, 1] >= on.offset_m[b] - 0.05).all()
    # It pays no offset cost and beats the plan by less than the plan margin.
    assert on.choice[b] == on.score[b]
    assert on.choice[b] - on.choice[0] < ON.plan_margin
    # Where the next lane is taken by the kerb, no pass is driven.
    occ, poses = history([parked()], road_half_width=2.0)
    narrow = check_plan(occ, poses, plan, GRID, ON).candidates
    assert narrow.kind[narrow.best] != "pass" and narrow.NC[narrow.best] == 1


def test_the_offset_ramp_is_quintic_and_reached_before_the_car():
    occ, poses = history([parked(x=20.0)], road_half_width=6.0)
    scene = forecast_scene(occ, poses, GRID, 6)
    b = parked_blocker(scene, PATH, V, ON)
    wps, offs, spd = pass_candidates(PATH, V, V, scene, ON, 6, 0.5)
    assert set(offs) == {b.left, b.right} and len(offs) == 2 * len(ON.speed_fractions)
    np.testing.assert_allclose(sorted(set(spd)), sorted(f * V for f in ON.speed_fractions))
    # At the plan's speed on a free pass the waypoints lie 5, 10, ... 30 m along; the offset
    # follows a quintic smoothstep over a ramp cut to end 1 m before the car (2.2 s at 10 m/s
    # would be 22 m).
    ramp = b.gap_m - 1.0
    x = V * 0.5 * np.arange(1, 7)
    u = np.clip(x / ramp, 0.0, 1.0)
    first = int(np.flatnonzero(offs == b.left)[0])  # its fastest run
    np.testing.assert_allclose(wps[first, :, 0], x, atol=1e-6)
    quintic = b.left * u**3 * (10 - 15 * u + 6 * u**2)
    np.testing.assert_allclose(wps[first, :, 1], quintic, atol=1e-9)
    assert wps[first, 0, 1] < b.left * u[0] ** 2 * (3 - 2 * u[0]) - 0.05  # a cubic starts steeper
