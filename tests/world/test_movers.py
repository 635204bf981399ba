"""Forecasts that move road users: the object constant-velocity warp and the movers references."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, OCC3D_CLASSES, GridSpec
from renderworld.metrics import ForecastMetric
from renderworld.world.baselines import warp_along_poses
from renderworld.world.forecast import warp_current
from renderworld.world.movers import (
    gt_movers_reference,
    gt_pose_movers_reference,
    object_constant_velocity_forecast,
)

# 1.6 m voxels (the coarse grid's size) on a small grid: 30 x 30 x 2.
GRID = GridSpec("test-movers", (-24.0, -24.0, -1.0), (24.0, 24.0, 3.0), (30, 30, 2))
VOX = 1.6
CAR, PED = OCC3D_CLASSES.index("car"), OCC3D_CLASSES.index("pedestrian")
ROAD = OCC3D_CLASSES.index("driveable_surface")
T, S = 5, 6


def _frame(objects) -> np.ndarray:
    """[X, Y, Z] road at z=0, each (class, ix, iy) object one voxel at z=1."""
    f = np.full(GRID.shape, FREE_ID, dtype=np.uint8)
    f[..., 0] = ROAD
    for cls, ix, iy in objects:
        if 0 <= ix < GRID.shape[0] and 0 <= iy < GRID.shape[1]:
            f[ix, iy, 1] = cls
    return f


def _scene(parked=(20, 10), mover=(10, 10), mover_step=(0, 1), ego_step=1, extra=()):
    """History [T, X, Y, Z] and poses [T, 3] of an ego driving ``ego_step`` voxels per frame
    along x; a parked car, a car moving ``mover_step`` voxels per frame (world), both given
    at their current-frame cells; ``extra`` objects as (class, ix, iy, (dx, dy) per frame)."""
    frames, poses = [], []
    for j in range(T - 1, -1, -1):  # j frames before the current one
        e = j * ego_step  # the ego was e voxels behind: world objects sit e voxels further ahead
        objs = [(CAR, parked[0] + e, parked[1])]
        objs.append((CAR, mover[0] - j * mover_step[0] + e, mover[1] - j * mover_step[1]))
        objs += [(c, ix - j * d[0] + e, iy - j * d[1]) for c, ix, iy, d in extra]
        frames.append(_frame(objs))
        poses.append((-j * ego_step * VOX, 0.0, 0.0))
    return np.stack(frames), np.array(poses)


def _cells(frame: np.ndarray, cls: int) -> set[tuple[int, int]]:
    return {(int(a), int(b)) for a, b in zip(*np.nonzero((frame == cls).any(-1)))}


def test_a_moving_car_moves_at_its_speed_and_a_parked_car_stays_put():
    hist, poses = _scene(mover_step=(0, 1))
    out = object_constant_velocity_forecast(hist, poses, S, GRID, lag=2)
    assert out.shape == (S, *GRID.shape) and out.dtype == np.uint8
    for k in range(1, S + 1):
        # Future frame k: the ego is k voxels further along x (constant velocity), the parked
        # car k voxels closer, the moving car also k voxels further along y.
        assert _cells(out[k - 1], CAR) == {(20 - k, 10), (10 - k, 10 + k)}, k
        assert (out[k - 1][..., 0][: GRID.shape[0] - k] == ROAD).all()  # the road stays


def test_two_voxels_per_frame_and_a_diagonal_mover():
    hist, poses = _scene(mover=(12, 8), mover_step=(2, 1))
    out = object_constant_velocity_forecast(hist, poses, S, GRID, lag=1)
    for k in (1, 2, 3):
        assert _cells(out[k - 1], CAR) == {(20 - k, 10), (12 + k, 8 + k)}, k


def test_an_object_leaves_the_grid():
    hist, poses = _scene(mover=(15, 27), mover_step=(0, 1), ego_step=0)
    out = object_constant_velocity_forecast(hist, poses, S, GRID, lag=2)
    assert _cells(out[0], CAR) == {(20, 10), (15, 28)}
    assert _cells(out[1], CAR) == {(20, 10), (15, 29)}
    for k in range(3, S + 1):  # gone: nothing wraps around or piles up at the border
        assert _cells(out[k - 1], CAR) == {(20, 10)}, k


def test_objects_match_their_own_class():
    # A pedestrian appears where the moving car was at t-2: it is the car's past's nearest
    # component, but only a past car can be a car's past (the pedestrian stays put).
    hist, poses = _scene(mover_step=(0, 1))
    hist[-1, 10, 8, 1] = PED
    out = object_constant_velocity_forecast(hist, poses, 3, GRID, lag=2)
    assert _cells(out[2], PED) == {(10 - 3, 8)}
    assert _cells(out[2], CAR) == {(20 - 3, 10), (10 - 3, 13)}


def test_a_parked_car_whose_footprint_changes_stays_put():
    # At t-2 the parked car covered one more cell: its centroid moved by half a voxel, which is
    # rasterisation, not motion.
    hist, poses = _scene()
    hist[-3, 20 + 2 + 1, 10, 1] = CAR  # frame t-2: the ego was 2 voxels behind
    out = object_constant_velocity_forecast(hist, poses, S, GRID, lag=2)
    for k in range(1, S + 1):
        assert (20 - k, 10) in _cells(out[k - 1], CAR) and (20 - k - 1, 10) not in _cells(
            out[k - 1], CAR
        ), k


def test_objects_match_one_to_one_closest_pairs_first():
    # The fast car's nearest past car is the parked car's; the parked car keeps its own past
    # (distance 0) and the fast car takes the other one.
    hist, poses = _scene(parked=(11, 8), mover=(10, 10), mover_step=(0, 2))
    out = object_constant_velocity_forecast(hist, poses, 3, GRID, lag=2)
    for k in (1, 2, 3):
        assert _cells(out[k - 1], CAR) == {(11 - k, 8), (10 - k, 10 + 2 * k)}, k


def test_history_only_and_batched_torch_input():
    hist, poses = _scene()
    one = object_constant_velocity_forecast(hist, poses, S, GRID)
    batch = torch.from_numpy(np.stack([hist, hist]))
    out = object_constant_velocity_forecast(batch, torch.from_numpy(np.stack([poses, poses])),
                                            S, GRID)  # fmt: skip
    assert isinstance(out, torch.Tensor) and out.shape == (2, S, *GRID.shape)
    assert np.array_equal(out[1].numpy(), one)
    with pytest.raises(ValueError, match="lag"):
        object_constant_velocity_forecast(hist, poses, S, GRID, lag=T)
    with pytest.raises(ValueError, match="history_poses"):
        object_constant_velocity_forecast(hist, poses[:-1], S, GRID)


def test_gt_movers_reference_pastes_the_future_movers():
    hist, _ = _scene(ego_step=0)
    current = hist[-1]
    future = np.stack([_frame([(CAR, 3, 3 + k), (PED, 25, 5)]) for k in range(S)])
    poses = np.zeros((S, 3))
    out = gt_movers_reference(current, future, poses, GRID)
    assert np.array_equal(out, future)  # static ego: the road, and exactly the future movers
    m = ForecastMetric(steps=S)
    m.update(out[None], future[None])
    assert m.compute()["movers_miou@1s"] == 1.0
    # The current frame's movers (cars at (20, 10) and (10, 10)) are removed, not left in place.
    assert _cells(out[0], CAR) == {(3, 3)}


def test_gt_pose_object_cv_reference_moves_the_movers_and_follows_the_gt_poses():
    # History: the ego drives 1 voxel per frame; the car at (10, 10) drives 1 voxel per frame
    # along y. The true future: the ego speeds up to 2 voxels per frame (constant velocity and
    # constant turn rate would say 1).
    hist, poses = _scene(mover_step=(0, 1))
    future = np.zeros((S, 3))
    future[:, 0] = 2 * VOX * np.arange(1, S + 1)
    out = gt_pose_movers_reference(hist, poses, future, GRID)
    assert out.shape == (S, *GRID.shape) and out.dtype == np.uint8
    static = warp_along_poses(hist[-1], future, GRID)
    for k in range(1, S + 1):
        # Future frame k: the parked car 2k voxels closer, the moving car 2k closer and k
        # voxels further along y (where the object-CV rule puts it), the road carried along.
        cars = {(20 - 2 * k, 10)} | ({(10 - 2 * k, 10 + k)} if 10 - 2 * k >= 0 else set())
        assert _cells(out[k - 1], CAR) == cars, k
        assert (out[k - 1][: GRID.shape[0] - 2 * k, :, 0] == ROAD).all()
        # The static GT-pose warp leaves the moving car where it is now.
        assert _cells(static[k - 1], CAR) == {(20 - 2 * k, 10)} | (
            {(10 - 2 * k, 10)} if 10 - 2 * k >= 0 else set()
        )
    # Batched torch input; the pose-warp model's own warp along the same poses is this row.
    hb, pb = torch.from_numpy(hist[None]), torch.from_numpy(poses[None])
    fb = torch.from_numpy(future[None])
    batched = gt_pose_movers_reference(hb, pb, fb, GRID)
    assert isinstance(batched, torch.Tensor) and np.array_equal(batched[0].numpy(), out)
    assert torch.equal(batched, warp_current(hb, pb, fb, GRID, "object_cv"))
    # Another movers rule through the same helper (a learned one gives its row this way): a
    # rule that moves nothing is the static GT-pose warp.

    def frozen(occ, hist_poses, steps, grid):
        return occ[:, -1:].expand(-1, steps, *occ.shape[2:])

    still = gt_pose_movers_reference(hb, pb, fb, GRID, movers_frames=frozen)
    assert np.array_equal(still[0].numpy(), static)
    with pytest.raises(ValueError, match="future_poses"):
        gt_pose_movers_reference(hb, pb, future[:, :2], GRID)
