import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, GridSpec
from renderworld.world import (
    constant_turn_rate_poses,
    constant_turn_rate_trajectory,
    constant_velocity_trajectory,
    copy_paste_forecast,
    warp_along_poses,
    warp_constant_velocity_forecast,
)

# 1 m voxels over [-4, 4) x [-4, 4) x [0, 2).
GRID = GridSpec("test", (-4.0, -4.0, 0.0), (4.0, 4.0, 2.0), (8, 8, 2))


def scene():
    occ = np.full(GRID.shape, FREE_ID, dtype=np.uint8)
    occ[5, 4, 0] = 4  # a car voxel centred at (1.5, 0.5)
    occ[0, 0, 1] = 15
    return occ


def test_copy_paste_repeats_and_copies():
    occ = scene()
    out = copy_paste_forecast(occ, steps=3)
    assert out.shape == (3, *GRID.shape) and out.dtype == np.uint8
    assert all(np.array_equal(out[k], occ) for k in range(3))
    out[0, 0, 0, 0] = 1
    assert occ[0, 0, 0] == FREE_ID  # not a view
    batched = copy_paste_forecast(torch.from_numpy(np.stack([occ, occ])), steps=2)
    assert isinstance(batched, torch.Tensor) and batched.shape == (2, 2, *GRID.shape)


def test_constant_velocity_trajectory():
    disp = np.array([[9.0, 9.0], [4.0, 1.0]])
    out = constant_velocity_trajectory(disp, steps=3)
    np.testing.assert_allclose(out, [[4, 1], [8, 2], [12, 3]])
    t = constant_velocity_trajectory(torch.tensor([[[1.0, 0.0]], [[0.0, -2.0]]]), steps=2)
    torch.testing.assert_close(
        t, torch.tensor([[[1.0, 0.0], [2.0, 0.0]], [[0.0, -2.0], [0.0, -4.0]]])
    )
    with pytest.raises(ValueError, match="displacements: expected"):
        constant_velocity_trajectory(np.zeros((0, 2)))


def test_warp_moves_static_world_backwards():
    occ = scene()
    out = warp_constant_velocity_forecast(occ, np.array([1.0, 0.0]), steps=2, grid=GRID)
    # Ego moves +1 m in x per step: the car at x=1.5 appears at x=0.5 then x=-0.5.
    assert out[0, 4, 4, 0] == 4 and out[1, 3, 4, 0] == 4
    assert (out[0] == 4).sum() == 1 and (out[1] == 4).sum() == 1
    # What enters from beyond the grid's front edge is free.
    assert (out[0, 7] == FREE_ID).all() and (out[1, 6:] == FREE_ID).all()
    # The manmade voxel at the back-left corner left the grid.
    assert (out == 15).sum() == 0


def test_warp_zero_motion_is_copy_and_lateral_motion():
    occ = scene()
    np.testing.assert_array_equal(
        warp_constant_velocity_forecast(occ, np.zeros(2), steps=2, grid=GRID),
        copy_paste_forecast(occ, steps=2),
    )
    out = warp_constant_velocity_forecast(occ, np.array([0.0, -1.0]), steps=1, grid=GRID)
    assert out[0, 5, 5, 0] == 4  # ego moved right (-y): the car appears further left (+y)


def test_warp_batched_torch_matches_unbatched():
    a, b = scene(), np.roll(scene(), 2, axis=1)
    d = np.array([[0.6, 0.2], [-1.3, 0.9]])
    batched = warp_constant_velocity_forecast(
        torch.from_numpy(np.stack([a, b])), torch.from_numpy(d), steps=3, grid=GRID
    )
    for i, occ in enumerate((a, b)):
        np.testing.assert_array_equal(
            batched[i].numpy(), warp_constant_velocity_forecast(occ, d[i], steps=3, grid=GRID)
        )


def test_warp_validation():
    with pytest.raises(ValueError, match="occupancy: expected"):
        warp_constant_velocity_forecast(np.zeros((4, 4, 2), np.uint8), np.zeros(2), grid=GRID)
    with pytest.raises(ValueError, match="last_displacement: expected"):
        warp_constant_velocity_forecast(scene(), np.zeros(3), grid=GRID)
    with pytest.raises(ValueError, match="last_displacement: expected finite"):
        warp_constant_velocity_forecast(scene(), np.array([np.nan, 0.0]), grid=GRID)
    with pytest.raises(TypeError, match="occupancy: expected a numpy array"):
        copy_paste_forecast([[1]])


# ---------------------------------------------------------------- pose warps, turn rate
def test_warp_along_poses_pure_rotation_of_a_known_grid():
    occ = np.full(GRID.shape, FREE_ID, dtype=np.uint8)
    occ[6, 4, 0] = 4  # car voxel centred at (2.5, 0.5): ahead of the ego
    # Target frame turned +90 deg (left) in place: what was ahead now lies on its right.
    out = warp_along_poses(occ, np.array([[0.0, 0.0, np.pi / 2]]), grid=GRID)
    # Target centre c maps to R(90) c = (-c_y, c_x); the car (2.5, 0.5) is at c = (0.5, -2.5).
    assert out.shape == (1, *GRID.shape) and out.dtype == np.uint8
    assert out[0, 4, 1, 0] == 4 and (out[0] == 4).sum() == 1
    # A full turn is the identity; 180 deg puts the car behind.
    np.testing.assert_array_equal(
        warp_along_poses(occ, np.array([[0.0, 0.0, 2 * np.pi]]), grid=GRID)[0], occ
    )
    back = warp_along_poses(occ, np.array([[0.0, 0.0, np.pi]]), grid=GRID)[0]
    assert back[1, 3, 0] == 4 and (back == 4).sum() == 1


def test_warp_along_poses_translation_equals_cv_warp_and_batches():
    occ = scene()
    d = np.array([1.0, -1.0])
    poses = np.array([[1.0, -1.0, 0.0], [2.0, -2.0, 0.0]])
    np.testing.assert_array_equal(
        warp_along_poses(occ, poses, grid=GRID),
        warp_constant_velocity_forecast(occ, d, steps=2, grid=GRID),
    )
    b = torch.from_numpy(np.stack([occ, occ]))
    bp = torch.tensor([[[0.0, 0.0, 0.0]], [[0.0, 0.0, np.pi]]])
    out = warp_along_poses(b, bp, grid=GRID, fill=0)
    assert isinstance(out, torch.Tensor) and out.shape == (2, 1, *GRID.shape)
    assert torch.equal(out[0, 0], b[0])


def test_warp_along_poses_rejects_bad_inputs():
    occ = scene()
    with pytest.raises(ValueError, match="poses: expected \\[S, 3\\]"):
        warp_along_poses(occ, np.zeros((2, 2)), grid=GRID)
    with pytest.raises(ValueError, match="poses: expected finite"):
        warp_along_poses(occ, np.array([[np.nan, 0.0, 0.0]]), grid=GRID)
    with pytest.raises(ValueError, match="occupancy: expected"):
        warp_along_poses(occ[:4], np.zeros((1, 3)), grid=GRID)
    with pytest.raises(TypeError, match="poses: expected a numpy array"):
        warp_along_poses(occ, [[0.0, 0.0, 0.0]], grid=GRID)


def test_constant_turn_rate_by_hand():
    # Last step: 1 m forward while turning +90 deg -> next steps turn 90 deg each.
    hist = np.array([[-1.0, 0.0, -np.pi / 2], [0.0, 0.0, 0.0]])
    poses = constant_turn_rate_poses(hist, steps=3)
    np.testing.assert_allclose(
        poses, [[0.0, 1.0, np.pi / 2], [-1.0, 1.0, np.pi], [-1.0, 0.0, -np.pi / 2]], atol=1e-12
    )
    np.testing.assert_allclose(constant_turn_rate_trajectory(hist, 3), poses[:, :2])
    # No heading change: the constant-velocity trajectory, heading fixed.
    straight = np.array([[-3.0, -1.0, 0.0], [-2.0, 0.5, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(
        constant_turn_rate_trajectory(straight, 4),
        constant_velocity_trajectory(np.diff(straight[:, :2], axis=0), 4),
    )
    t = constant_turn_rate_poses(torch.from_numpy(np.stack([hist, hist])).float(), steps=2)
    assert isinstance(t, torch.Tensor) and t.shape == (2, 2, 3) and t.dtype == torch.float32
    with pytest.raises(ValueError, match="history_poses: expected \\[T>=2, 3\\]"):
        constant_turn_rate_poses(np.zeros((1, 3)))
