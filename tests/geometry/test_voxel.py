import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from renderworld.constants import GRIDS, OCC3D_GRID, GridSpec
from renderworld.geometry import VoxelGrid


def test_occ3d_grid_centres_and_corners():
    g = VoxelGrid(OCC3D_GRID)
    np.testing.assert_allclose(g.voxel_size, [0.4, 0.4, 0.4])
    c = g.centres()
    assert c.shape == (200, 200, 16, 3)
    np.testing.assert_allclose(c[0, 0, 0], [-39.8, -39.8, -0.8])
    np.testing.assert_allclose(c[-1, -1, -1], [39.8, 39.8, 5.2])
    idx, inside = g.points_to_index(np.array([[0.0, 0.0, 0.0], [40.0, 0, 0], [-40.0, 0, 0]]))
    assert idx[0].tolist() == [100, 100, 2]
    assert inside.tolist() == [True, False, True]  # half-open: max is outside


def test_out_of_range_and_nan_points_are_outside():
    g = VoxelGrid(OCC3D_GRID)
    pts = np.array([[np.nan, 0, 0], [0, 0, 6.0], [0, 0, -1.01], [1e9, 0, 0]])
    idx, inside = g.points_to_index(pts)
    assert not inside.any()
    assert (idx >= 0).all() and (idx < np.array(g.shape)).all()
    idx_t, inside_t = g.points_to_index(torch.tensor(pts, dtype=torch.float32))
    assert not inside_t.any()


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(sorted(GRIDS)), data=st.data())
def test_index_centre_round_trip(name, data):
    g = VoxelGrid(GRIDS[name])
    ijk = np.array([[data.draw(st.integers(0, n - 1)) for n in g.shape]])
    centre = g.index_to_centre(ijk)
    back, inside = g.points_to_index(centre)
    assert inside.all() and (back == ijk).all()
    back_t, inside_t = g.points_to_index(torch.as_tensor(centre, dtype=torch.float64))
    assert inside_t.all() and back_t.tolist() == ijk.tolist()
    assert g.flat_index(ijk)[0] == np.ravel_multi_index(tuple(ijk[0]), g.shape)


def test_bad_spec_is_rejected():
    with pytest.raises(ValueError, match="range_max must exceed"):
        VoxelGrid(GridSpec("bad", (0, 0, 0), (0, 1, 1), (1, 1, 1)))
    with pytest.raises(ValueError, match="spec.shape"):
        VoxelGrid(GridSpec("bad", (0, 0, 0), (1, 1, 1), (0, 1, 1)))
