"""``track_movers`` keeps the tracks of its last histories: the same history, whatever its label
dtype, gives the same tracks back without tracking again; another one is tracked afresh."""

import numpy as np
import pytest

import renderworld.world.tracks as tracks_mod
from renderworld.world.tracks import CACHE_SIZE, clear_track_cache, track_movers

from ..planning.test_checked import CAR, GRID, history


def _history(x0=12.0):
    return history([(CAR, lambda t: (x0 + 6.0 * t, -1.6), (3, 2))], road_half_width=6.0)


def test_the_same_history_is_tracked_once(monkeypatch):
    clear_track_cache()
    calls = []
    real = tracks_mod._track

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(tracks_mod, "_track", counting)
    occ, poses = _history()
    first = track_movers(occ, poses, GRID)
    again = track_movers(occ.astype(np.int16), poses.astype(np.float64), GRID)
    assert len(calls) == 1 and len(first) == len(again) >= 1
    for a, b in zip(first, again, strict=True):
        assert a is b  # the kept tracks themselves
        with pytest.raises(ValueError):
            a.velocity[0] = 1.0  # read-only: no caller can change another's tracks
    # Another history, or other arguments, are tracked afresh and equal the uncached tracking.
    occ2, poses2 = _history(15.0)
    other = track_movers(occ2, poses2, GRID)
    track_movers(occ, poses, GRID, min_shift_voxels=2.0)
    assert len(calls) == 3
    ref = real(occ2, poses2, GRID, 0.5, 1.0, tracks_mod.SPLIT_SPEED_MPS)
    for a, b in zip(other, ref, strict=True):
        np.testing.assert_array_equal(a.centroids, b.centroids)
        np.testing.assert_array_equal(a.velocity, b.velocity)
    # The cache stays bounded, and clearing it tracks again.
    for k in range(CACHE_SIZE + 2):
        track_movers(*_history(20.0 + k), GRID)
    assert len(tracks_mod._CACHE) == CACHE_SIZE
    clear_track_cache()
    track_movers(occ, poses, GRID)
    assert len(calls) == 3 + CACHE_SIZE + 2 + 1
