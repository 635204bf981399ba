"""The batched tracker equals its reference twin, the scalar kinematic model, bit for bit."""

import numpy as np
import pytest

from renderworld.planning.kinematics import EgoState, KinematicLimits, track_plan
from renderworld.planning.tracking import track_plans


def _scalar(states, waypoints, limits, steps):
    out, sat = [], []
    for st, wp in zip(states, waypoints):
        tracked, n = track_plan(EgoState(*st), wp, limits, steps)
        out.append([[s.x, s.y, s.yaw, s.speed] for s in tracked])
        sat.append(n)
    return np.array(out), np.array(sat)


@pytest.mark.parametrize("steps", [5, 30])
def test_batched_tracking_equals_the_scalar_model(steps):
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
    got, got_sat = track_plans(states, waypoints, limits, steps)
    want, want_sat = _scalar(states, waypoints, limits, steps)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_sat, want_sat)
    assert got_sat.max() > 0 and (got_sat == 0).any()  # both branches were exercised


def test_bad_shapes_name_the_argument():
    lim = KinematicLimits()
    with pytest.raises(ValueError, match="states"):
        track_plans(np.zeros((2, 3)), np.zeros((2, 6, 2)), lim, 5)
    with pytest.raises(ValueError, match="waypoints"):
        track_plans(np.zeros((2, 4)), np.zeros((3, 6, 2)), lim, 5)
