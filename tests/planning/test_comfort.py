"""The fast comfort signals equal their reference twin (scipy's Savitzky-Golay filters)."""

import numpy as np
import pytest

from renderworld.planning.comfort import COMFORT_BOUNDS, comfort_signals, comfort_signals_fast


def _states(rng, shape):
    st = np.cumsum(rng.normal(0.0, 0.1, (*shape, 4)), axis=-2)
    st[..., 3] = np.abs(st[..., 3]) + 5.0
    return st


@pytest.mark.parametrize("n", [5, 7, 8, 12, 41])
def test_fast_signals_equal_the_reference(n):
    rng = np.random.default_rng(n)
    for shape in ((n,), (3, n), (2, 4, n)):  # one window, and batches of them
        st = _states(rng, shape)
        want, got = comfort_signals(st), comfort_signals_fast(st)
        assert set(got) == set(COMFORT_BOUNDS)
        for k in want:
            assert got[k].shape == want[k].shape
            np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1.01e-8)


def test_a_hard_brake_and_a_sharp_turn_read_the_same_either_way():
    t = np.arange(41) * 0.1
    v = np.maximum(10.0 - 6.0 * np.maximum(t - 1.0, 0.0), 0.0)  # brakes at 6 m/s^2 from 1 s
    yaw = 0.6 * np.clip(t - 2.0, 0.0, 1.0)  # turns 0.6 rad in one second from 2 s
    st = np.stack([np.cumsum(v) * 0.1, np.zeros(41), yaw, v], -1)
    want, got = comfort_signals(st), comfort_signals_fast(st)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1.01e-8)
    assert want["lon_accel"].min() < COMFORT_BOUNDS["lon_accel"][0]  # the case breaks bounds
    assert np.abs(want["yaw_accel"]).max() > COMFORT_BOUNDS["yaw_accel"][1]


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="states"):
        comfort_signals_fast(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="dt"):
        comfort_signals_fast(np.zeros((6, 4)), dt=0.0)
