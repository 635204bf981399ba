"""The batched tracker equals its reference twin, the scalar kinematic model, bit for bit."""

import numpy as np
import pytest

from renderworld.constants import KEYFRAME_DT
from renderworld.planning.check import comfort_excess
from renderworld.planning.kinematics import (
    EgoState,
    KinematicLimits,
    hermite_tangents,
    track_plan,
)
from renderworld.planning.tracking import track_plans


def _scalar(states, waypoints, limits, steps, spline=False):
    out, sat = [], []
    for st, wp in zip(states, waypoints):
        tracked, n = track_plan(EgoState(*st), wp, limits, steps, spline)
        out.append([[s.x, s.y, s.yaw, s.speed] for s in tracked])
        sat.append(n)
    return np.array(out), np.array(sat)


@pytest.mark.parametrize("spline", [False, True])
@pytest.mark.parametrize("steps", [5, 30])
def test_batched_tracking_equals_the_scalar_model(steps, spline):
    rng = np.random.default_rng(0)
    n = 60
    states = np.stack([rng.normal(0, 5, n), rng.normal(0, 5, n), rng.uniform(-3, 3, n),
                       rng.uniform(0, 15, n)], 1)  # fmt: skip
    states[::7, 3] = 0.0  # standing starts
    waypoints = np.cumsum(rng.normal(2, 3, (n, 6, 2)), 1) + states[:, None, :2]
    waypoints[::5] = states[::5, None, :2]  # plans that stop at once: saturated braking
    gentle = states[1::5, :2, None] + np.arange(1, 7)[None, None] * 1.5  # feasible, exact
    waypoints[1::5] = np.moveaxis(gentle, 1, 2)
    limits = KinematicLimits()
    got, got_sat = track_plans(states, waypoints, limits, steps, spline)
    want, want_sat = _scalar(states, waypoints, limits, steps, spline)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_sat, want_sat)
    assert got_sat.max() > 0 and (got_sat == 0).any()  # both branches were exercised


def test_bad_shapes_name_the_argument():
    lim = KinematicLimits()
    with pytest.raises(ValueError, match="states"):
        track_plans(np.zeros((2, 3)), np.zeros((2, 6, 2)), lim, 5)
    with pytest.raises(ValueError, match="waypoints"):
        track_plans(np.zeros((2, 4)), np.zeros((3, 6, 2)), lim, 5)


def _knot_accels(pts, vel, h):
    """Acceleration [M-2, 2] at each inner knot from the left and from the right segment."""
    left = (6 * pts[:-2] + 2 * h * vel[:-2] - 6 * pts[1:-1] + 4 * h * vel[1:-1]) / h**2
    right = (-6 * pts[1:-1] - 4 * h * vel[1:-1] + 6 * pts[2:] - 2 * h * vel[2:]) / h**2
    return left, right


def test_spline_tangents_make_acceleration_continuous_at_every_waypoint():
    """The C2 spline: the acceleration from either side of an inner waypoint agrees (heading
    rate without jumps), it ends with zero acceleration and starts with the current velocity;
    Catmull-Rom's tangents leave jumps on the same uneven plan."""
    h = KEYFRAME_DT
    pts = np.array([[0, 0], [3.0, 0.1], [6.5, 0.6], [9.5, 1.8], [12.0, 3.6], [14.0, 6.0],
                    [15.5, 8.8]])  # fmt: skip
    v0 = np.array([6.0, 0.0])
    vel = hermite_tangents(pts[None], v0[None], h, spline=True)[0]
    np.testing.assert_array_equal(vel[0], v0)
    left, right = _knot_accels(pts, vel, h)
    np.testing.assert_allclose(left, right, atol=1e-9)
    end = (6 * pts[-2] + 2 * h * vel[-2] - 6 * pts[-1] + 4 * h * vel[-1]) / h**2
    np.testing.assert_allclose(end, 0.0, atol=1e-9)
    cr = hermite_tangents(pts[None], v0[None], h, spline=False)[0]
    left, right = _knot_accels(pts, cr, h)
    assert np.abs(left - right).max() > 1.0  # m/s^2: Catmull-Rom jumps


def test_a_turn_into_a_junction_is_comfortable_to_the_end_of_the_plan():
    """A plan at 5.5 m/s that drives straight for 1 s, then turns right on a 12 m radius: both
    curves drive the plan within every NAVSIM bound to its end, and the heading keeps turning
    right through the last segment (the end tangent is the arc's through the last three
    waypoints: along the last chord the curve straightened there and swung the heading back,
    1.4x the yaw-acceleration bound; the C2 spline's natural end straightens gently)."""
    v, r, straight = 5.5, 12.0, 5.5
    s = v * 0.5 * np.arange(1, 7)
    turn = np.maximum(s - straight, 0.0) / r
    wp = np.stack([np.minimum(s, straight) + r * np.sin(turn), -r * (1 - np.cos(turn))], 1)
    past = np.stack([np.linspace(-2 * v, 0, 21), np.zeros(21), np.zeros(21), np.full(21, v)], 1)
    start = np.array([[0.0, 0.0, 0.0, v]])
    for spline in (False, True):
        states, _ = track_plans(start, wp[None], KinematicLimits(), 30, spline)
        worst, name = comfort_excess(states, past, worst_name=True)
        assert worst[0] < 0.9, (spline, worst, name)
        np.testing.assert_allclose(states[0, 4::5, :2], wp[:6], atol=0.05)  # both drive the plan
    states, _ = track_plans(start, wp[None], KinematicLimits(), 30)
    yaw_rate = np.diff(states[0, :, 2]) / 0.1  # rad/s; the turn's own is -v / r
    assert (yaw_rate[-5:] < -0.7 * v / r).all(), yaw_rate[-5:]


def test_the_end_tangent_follows_the_arc_through_the_last_waypoints():
    """On a circle the end tangent is the circle's (the chord's direction is half a segment's
    turn behind); a plan that stops, folds back or has two knots keeps its last chord."""
    h = KEYFRAME_DT
    a = np.arange(7) * 0.15  # radians per knot on a 10 m radius, 1.5 m per knot
    pts = np.stack([10 * np.sin(a), 10 * (1 - np.cos(a))], 1)
    vel = hermite_tangents(pts[None], np.array([[3.0, 0.0]]), h, spline=False)[0]
    np.testing.assert_allclose(np.arctan2(vel[-1, 1], vel[-1, 0]), a[-1], atol=1e-12)
    np.testing.assert_allclose(np.hypot(*vel[-1]), np.hypot(*(pts[-1] - pts[-2])) / h)
    for last in ([3.0, 0.005], [2.0, 0.5]):  # a stop under 1 cm; a path folding back
        p = np.array([[0.0, 0.0], [1.5, 0.0], [3.0, 0.0], last])
        v = hermite_tangents(p[None], np.array([[3.0, 0.0]]), h, spline=False)[0, -1]
        np.testing.assert_allclose(v, (p[-1] - p[-2]) / h, atol=1e-12)
    two = np.array([[0.0, 0.0], [1.5, 0.3]])
    np.testing.assert_allclose(
        hermite_tangents(two[None], np.array([[3.0, 0.0]]), h, spline=False)[0, -1],
        (two[1] - two[0]) / h,
    )
