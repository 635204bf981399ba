"""Grid down-sampling rule: any non-free wins, mode with ties to the lower id; masks any."""

import numpy as np
import pytest

from renderworld.constants import FREE_ID, GRIDS, OCC3D_GRID
from renderworld.data import downsample_mask, downsample_occupancy
from renderworld.data.downsample import grid_factor


def downsample_reference(sem, f):
    """Loop reference: per coarse voxel count the non-free classes of its fine voxels."""
    fx, fy, fz = f
    out = np.full((sem.shape[0] // fx, sem.shape[1] // fy, sem.shape[2] // fz), FREE_ID, np.uint8)
    for i, j, k in np.ndindex(out.shape):
        block = sem[i * fx : (i + 1) * fx, j * fy : (j + 1) * fy, k * fz : (k + 1) * fz].ravel()
        counts = np.bincount(block[block != FREE_ID], minlength=FREE_ID)
        if counts.sum():
            out[i, j, k] = int(np.argmax(counts))  # first maximum = lower id
    return out


def test_thin_road_layer_survives_in_z():
    sem = np.full((8, 8, 16), FREE_ID, np.uint8)
    sem[:, :, 2] = 11  # one voxel thick driveable surface
    coarse = downsample_occupancy(sem, 4)
    assert coarse.shape == (2, 2, 4)
    assert (coarse[:, :, 0] == 11).all() and (coarse[:, :, 1:] == FREE_ID).all()


def test_mode_and_ties_go_to_the_lower_id():
    sem = np.full((2, 2, 2), FREE_ID, np.uint8)
    sem.flat[:3] = [4, 4, 16]  # car twice, vegetation once, 5 free
    assert downsample_occupancy(sem, 2).item() == 4
    sem.flat[:4] = [16, 16, 4, 4]  # tie car / vegetation -> car (4 < 16)
    assert downsample_occupancy(sem, 2).item() == 4
    sem.flat[:4] = [0, 10, FREE_ID, FREE_ID]  # tie others / truck -> others (0)
    assert downsample_occupancy(sem, 2).item() == 0
    sem[:] = FREE_ID
    assert downsample_occupancy(sem, 2).item() == FREE_ID


def test_mask_any_observed():
    mask = np.zeros((4, 4, 4), np.uint8)
    mask[3, 0, 1] = 1
    out = downsample_mask(mask, 2)
    assert out.dtype == bool and out.shape == (2, 2, 2)
    assert out.sum() == 1 and out[1, 0, 0]


@pytest.mark.parametrize("factor", [(2, 2, 2), (4, 4, 2), (2, 4, 1), 1])
def test_matches_loop_reference(factor):
    rng = np.random.default_rng(7)
    sem = rng.choice([0, 4, 11, 16, FREE_ID], size=(8, 8, 4), p=[0.05, 0.1, 0.1, 0.05, 0.7])
    sem = sem.astype(np.uint8)
    f = (factor,) * 3 if isinstance(factor, int) else factor
    np.testing.assert_array_equal(downsample_occupancy(sem, factor), downsample_reference(sem, f))


def test_batched_leading_dims():
    rng = np.random.default_rng(1)
    sem = rng.integers(0, 18, (3, 8, 8, 4)).astype(np.uint8)
    out = downsample_occupancy(sem, (2, 2, 2))
    assert out.shape == (3, 4, 4, 2)
    for b in range(3):
        np.testing.assert_array_equal(out[b], downsample_reference(sem[b], (2, 2, 2)))
    assert downsample_mask(sem > 9, 2).shape == (3, 4, 4, 2)


def test_occ3d_to_named_grids():
    assert grid_factor(OCC3D_GRID.shape, GRIDS["coarse"]) == (4, 4, 4)
    assert grid_factor(OCC3D_GRID.shape, GRIDS["quarter"]) == (4, 4, 2)
    sem = np.full(OCC3D_GRID.shape, FREE_ID, np.uint8)
    sem[100, 100, 0] = 4
    out = downsample_occupancy(sem, grid_factor(sem.shape, GRIDS["half"]))
    assert out.shape == (100, 100, 8) and out[50, 50, 0] == 4 and (out != FREE_ID).sum() == 1


def test_validation_messages():
    sem = np.zeros((4, 4, 4), np.uint8)
    with pytest.raises(ValueError, match=r"semantics: shape \(4, 4, 4\) is not divisible"):
        downsample_occupancy(sem, 3)
    with pytest.raises(ValueError, match=r"semantics: expected ids 0..17, got range 18..18"):
        downsample_occupancy(np.full((2, 2, 2), 18, np.uint8), 2)
    with pytest.raises(ValueError, match=r"semantics: expected integer class ids"):
        downsample_occupancy(sem.astype(float), 2)
    with pytest.raises(ValueError, match=r"factor: expected positive integers"):
        downsample_mask(sem, 0)
    with pytest.raises(ValueError, match=r"factor: expected an int or 3 ints"):
        downsample_mask(sem, (2, 2))
    with pytest.raises(ValueError, match=r"grid: coarse shape .* is not an integer down-sampling"):
        grid_factor((10, 10, 10), GRIDS["coarse"])
