"""The learned plan's hold-back with its braking spread over the horizon
(``CheckConfig.ease_hold_decel``, :mod:`renderworld.planning.ease`).

Hand-made scenes on the demo's coarse grid (the ego along +x at 10 m/s), as in ``test_relax``.
"""

import numpy as np
import pytest

from renderworld.planning.candidates import CheckConfig, PlanPath, leaders
from renderworld.planning.checked import check_plan
from renderworld.planning.ease import ease_hold, leaders_move_on
from renderworld.planning.idm import FRONT
from renderworld.planning.scene import forecast_scene

from .test_checked import CAR, GRID, PED, V, history, straight_plan

T = np.arange(1, 7) * 0.5


def speeds(s):
    """[S] mean speed over each half second of arc lengths [S] (m/s)."""
    return np.diff(np.r_[0.0, s]) / 0.5


def test_the_ease_ends_where_the_hold_back_does_at_one_constant_deceleration():
    v = np.array([6.5, 6.2, 6.0, 6.0, 6.0, 6.0])  # IDM: hardest first, then easing off
    held = np.cumsum(v) * 0.5
    plan = V * T
    eased = ease_hold(held, plan, V, 4.0, 0.5)
    assert eased[-1] == pytest.approx(held[-1])
    decel = -np.diff(np.r_[V, speeds(eased)]) / 0.5
    np.testing.assert_allclose(decel[1:], decel[1], atol=1e-9)  # constant after the first step
    assert decel.max() < 3.0 and (-np.diff(np.r_[V, v]) / 0.5).max() >= 7.0
    # Ahead of IDM in between, never beyond the learned plan.
    assert (eased[:-1] > held[:-1]).all() and (eased <= plan + 1e-12).all()


def test_a_stop_within_the_horizon_stands_where_the_hold_back_stands():
    held = np.array([4.0, 6.5, 7.5, 7.8, 7.8, 7.8])  # IDM stops at 7.8 m
    eased = ease_hold(held, V * T, 7.0, 4.0, 0.5)  # 7 m/s to a stand in 7.8 m: 3.14 m/s^2
    np.testing.assert_allclose(eased[-2:], 7.8, rtol=1e-12)  # standing from 2.23 s
    decel = 7.0**2 / (2 * 7.8)
    np.testing.assert_allclose(eased[:4], 7.0 * T[:4] - 0.5 * decel * T[:4] ** 2, rtol=1e-12)


def test_a_stop_harder_than_the_knob_keeps_the_hold_back_and_bad_input_is_named():
    held = np.array([4.0, 6.0, 6.5, 6.5, 6.5, 6.5])  # 10 m/s to a stand in 6.5 m: 7.7 m/s^2
    assert ease_hold(held, V * T, V, 4.0, 0.5) is held
    # Nothing to brake for, or a standing ego: unchanged.
    np.testing.assert_array_equal(ease_hold(V * T, V * T, V, 4.0, 0.5), V * T)
    np.testing.assert_array_equal(ease_hold(np.zeros(6), np.zeros(6), 0.0, 4.0, 0.5), 0.0)
    with pytest.raises(ValueError, match="s_held"):
        ease_hold(np.zeros(5), V * T, V, 4.0, 0.5)
    with pytest.raises(ValueError, match="max_decel"):
        ease_hold(held, V * T, V, 0.0, 0.5)


def test_the_checked_plan_behind_a_slower_car_brakes_evenly_instead_of_hardest_first():
    lead = (CAR, lambda t: (FRONT + 14.0 + 7.0 * t, 0.0), (3, 2))  # 14 m ahead, 3 m/s slower
    occ, poses = history([lead])
    plan = straight_plan()
    off = check_plan(occ, poses, plan, GRID, CheckConfig()).candidates
    on = check_plan(occ, poses, plan, GRID, CheckConfig(ease_hold_decel=4.0)).candidates
    v_off, v_on = speeds(np.hypot(*off.waypoints[0].T)), speeds(np.hypot(*on.waypoints[0].T))
    first_off, first_on = (V - v_off[0]) / 0.5, (V - v_on[0]) / 0.5
    assert first_on < first_off - 0.5  # a softer start
    assert np.hypot(*on.waypoints[0, -1]) == pytest.approx(
        np.hypot(*off.waypoints[0, -1]), abs=0.05
    )
    assert CheckConfig().ease_hold_decel is None  # off unless chosen


def test_behind_a_standing_car_the_hold_back_keeps_idms_early_braking():
    parked = (CAR, lambda t: (FRONT + 25.0, 0.0), (3, 2))
    slower = (CAR, lambda t: (FRONT + 14.0 + 7.0 * t, 0.0), (3, 2))
    plan = straight_plan()
    for objects, eased in (([parked], False), ([slower], True)):
        occ, poses = history(objects)
        scene = forecast_scene(occ, poses, GRID, 6)
        path = PlanPath(np.concatenate([np.zeros((1, 2)), plan[:, :2]]), 60.0)
        (lead,) = leaders(scene, path, (0.0,), CheckConfig(), 3.0)
        assert leaders_move_on(lead, path.arcs_of(plan[:, :2]), V, 0.5) is eased
        off = check_plan(occ, poses, plan, GRID, CheckConfig()).candidates.waypoints[0]
        on = check_plan(occ, poses, plan, GRID, CheckConfig(ease_hold_decel=4.0))
        assert np.array_equal(on.candidates.waypoints[0], off) is not eased
    # No leader at all: nothing to ease behind.
    occ, poses = history([])
    scene = forecast_scene(occ, poses, GRID, 6)
    (lead,) = leaders(scene, path, (0.0,), CheckConfig(), 3.0)
    assert not leaders_move_on(lead, path.arcs_of(plan[:, :2]), V, 0.5)


def test_behind_a_car_ahead_with_a_pedestrian_about_to_cross_nothing_is_eased():
    slower = (CAR, lambda t: (FRONT + 24.0 + 7.0 * t, 0.0), (3, 2))
    walker = (PED, lambda t: (FRONT + 12.0, -4.0 + 1.4 * t), (1, 1))  # kerb to path in ~2 s
    plan = straight_plan()
    path = PlanPath(np.concatenate([np.zeros((1, 2)), plan[:, :2]]), 60.0)
    for objects, eased in (([slower], True), ([slower, walker], False)):
        occ, poses = history(objects)
        (lead,) = leaders(forecast_scene(occ, poses, GRID, 6), path, (0.0,), CheckConfig(), 3.0)
        assert leaders_move_on(lead, path.arcs_of(plan[:, :2]), V, 0.5) is eased
