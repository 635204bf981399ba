"""Comfort of 10 Hz ego states, NAVSIM's way (``pdm_comfort_metrics``), over 4 s windows.

The closed loop judges an episode with it (:mod:`renderworld.sim.closed_loop.scores`); the
forecast-checked planner judges its candidates with the same signals
(:mod:`renderworld.planning.check`).

NAVSIM judges one 4 s trajectory at 10 Hz (41 states). Here windows of 41 states slide over the
episode's 10 Hz states, one starting at every plan (every 0.5 s = 5 states) while a whole window
fits, plus one ending at the last state so that every state is judged; an episode shorter than
4 s is one window of all its states (NAVSIM: filter windows shortened to the states there are).
An episode is comfortable when every window is; one with fewer than 5 states (under 0.4 s
driven) is not judged (comfortable).

Per window of ``n`` states (speed ``v``, m/s; heading unwrapped, rad; ``dt`` = 0.1 s), the raw
longitudinal acceleration is ``gradient(v)`` and the raw lateral one ``v x gradient(yaw)``
(m/s^2), then NAVSIM's Savitzky-Golay filters (``scipy.signal.savgol_filter``, mode ``interp``):

========== ========================================================== ========================
quantity    smoothing (window length, polynomial order, derivative)    bound (NAVSIM's)
========== ========================================================== ========================
lon_accel   acceleration: (n, 2)                                       (-4.05, 2.40) m/s^2
lat_accel   lateral acceleration: (n, 2)                               (-4.89, 4.89) m/s^2
jerk        |acceleration| (8, 2), then (n, 2, 1st derivative)         (-8.37, 8.37) m/s^3
lon_jerk    acceleration (8, 2), then (n, 2, 1st derivative)           (-4.13, 4.13) m/s^3
yaw_rate    heading: (5, 2, 1st derivative)                            (-0.95, 0.95) rad/s
yaw_accel   heading: (5, 3, 2nd derivative)                            (-1.93, 1.93) rad/s^2
========== ========================================================== ========================

Values are rounded to 1e-8 and must lie strictly inside the bounds (NAVSIM's ``_within_bound``).
NAVSIM reads the accelerations from its simulator's state, whose kinematic bicycle model sets
the rear axle's lateral acceleration to 0 (so its lateral bound, and the lateral part of its
jerk magnitude, never act); here the lateral acceleration is the centripetal ``v x yaw rate``,
so both act on turns.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.signal import savgol_filter

from renderworld.planning.kinematics import SIM_DT

__all__ = [
    "COMFORT_BOUNDS",
    "COMFORT_STRIDE",
    "COMFORT_WINDOW",
    "comfort_signals",
    "comfort_signals_fast",
    "comfort_violations",
    "comfort_windows",
]

#: (low, high) of each comfort quantity, exclusive (NAVSIM's bounds; module docstring: units).
COMFORT_BOUNDS = {
    "lon_accel": (-4.05, 2.40),
    "lat_accel": (-4.89, 4.89),
    "jerk": (-8.37, 8.37),
    "lon_jerk": (-4.13, 4.13),
    "yaw_rate": (-0.95, 0.95),
    "yaw_accel": (-1.93, 1.93),
}
#: States in one window: 4 s at 10 Hz, both ends included (NAVSIM's trajectory).
COMFORT_WINDOW = 41
#: States between window starts: one plan (0.5 s).
COMFORT_STRIDE = 5
_MIN_STATES = 5


def comfort_windows(n: int, window: int = COMFORT_WINDOW, stride: int = COMFORT_STRIDE) -> list:
    """``[(start, stop)]`` state index ranges of the windows over ``n`` states (module docstring).

    Raises:
        ValueError: naming ``window`` or ``stride`` when not positive.
    """
    if window < 1:
        raise ValueError(f"window: expected at least 1 state, got {window}")
    if stride < 1:
        raise ValueError(f"stride: expected at least 1 state, got {stride}")
    if n <= window:
        return [(0, n)] if n > 0 else []
    starts = list(range(0, n - window + 1, stride))
    if starts[-1] != n - window:
        starts.append(n - window)
    return [(a, a + window) for a in starts]


def comfort_signals(states: np.ndarray, dt: float = SIM_DT) -> dict[str, np.ndarray]:
    """NAVSIM-smoothed comfort quantities [n] of one window (module docstring: the filters).

    Args:
        states: [..., n, 4] (x, y, yaw, speed) 10 Hz states, scene frame, rear axle; n >= 5
            (leading dimensions: several trajectories at once).
        dt: seconds between states.

    Returns:
        Each quantity [..., n].

    Raises:
        ValueError: naming ``states`` when it is not [..., n >= 5, 4], or ``dt`` when not
            positive.
    """

    def sg(x, n, window, order, deriv=0):
        return savgol_filter(x, min(window, n), order, deriv=deriv, delta=dt, axis=-1)

    return _signals(states, dt, sg)


@lru_cache(maxsize=128)
def _savgol_matrix(n: int, window: int, order: int, deriv: int, dt: float) -> np.ndarray:
    """[n, n] M with ``savgol_filter(x, ...) == M @ x`` for signals of n samples (the filter,
    its ``interp`` edges included, is linear: M's columns are its responses to unit impulses)."""
    m = savgol_filter(np.eye(n), min(window, n), order, deriv=deriv, delta=dt, axis=0)
    m.setflags(write=False)
    return m


def comfort_signals_fast(states: np.ndarray, dt: float = SIM_DT) -> dict[str, np.ndarray]:
    """:func:`comfort_signals` (its reference twin and the tests' oracle) with each
    Savitzky-Golay filter as one cached matrix product: the forecast-checked planner judges
    dozens of candidates in several windows per plan. Equal to it up to float round-off
    (below 1e-14 of the signal's size, measured) before both round to 1e-8.

    Args / Returns / Raises: as :func:`comfort_signals`.
    """

    def sg(x, n, window, order, deriv=0):
        return x @ _savgol_matrix(n, window, order, deriv, float(dt)).T

    return _signals(states, dt, sg)


def _signals(states, dt, sg) -> dict[str, np.ndarray]:
    """The quantities of :func:`comfort_signals` with ``sg(x, n, window, order, deriv)`` as the
    Savitzky-Golay filter along the last axis."""
    states = np.asarray(states, dtype=np.float64)
    if states.ndim < 2 or states.shape[-2] < _MIN_STATES or states.shape[-1] != 4:
        raise ValueError(
            f"states: expected shape [..., n >= {_MIN_STATES}, 4], got {list(states.shape)}"
        )
    if not dt > 0:
        raise ValueError(f"dt: expected a positive step in seconds, got {dt}")
    n = states.shape[-2]
    v, yaw = states[..., 3], np.unwrap(states[..., 2], axis=-1)
    lon = np.gradient(v, dt, axis=-1)
    lat = v * np.gradient(yaw, dt, axis=-1)
    out = {
        "lon_accel": sg(lon, n, n, 2),
        "lat_accel": sg(lat, n, n, 2),
        "jerk": sg(sg(np.hypot(lon, lat), n, 8, 2), n, n, 2, 1),
        "lon_jerk": sg(sg(lon, n, 8, 2), n, n, 2, 1),
        "yaw_rate": sg(yaw, n, 5, 2, 1),
        "yaw_accel": sg(yaw, n, 5, 3, 2),
    }
    return {k: np.round(q, 8) for k, q in out.items()}


def comfort_violations(states: np.ndarray, dt: float = SIM_DT) -> dict[str, int]:
    """Per bound of :data:`COMFORT_BOUNDS`, the 10 Hz states out of it in at least one window.

    All zero means comfortable (every window within every bound); fewer than 5 states: all zero.

    Args:
        states: [N, 4] (x, y, yaw, speed) 10 Hz states of an episode.
        dt: seconds between states.
    """
    states = np.asarray(states, dtype=np.float64)
    n = len(states)
    bad = {k: np.zeros(n, dtype=bool) for k in COMFORT_BOUNDS}
    if n >= _MIN_STATES:
        for a, b in comfort_windows(n):
            q = comfort_signals(states[a:b], dt)
            for k, (lo, hi) in COMFORT_BOUNDS.items():
                bad[k][a:b] |= ~((q[k] > lo) & (q[k] < hi))
    return {k: int(m.sum()) for k, m in bad.items()}
