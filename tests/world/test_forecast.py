"""The pose-warp forecaster (renderworld.world.forecast): warp, movers, composition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, OCC3D_CLASSES
from renderworld.world.baselines import warp_along_poses
from renderworld.world.forecast import (
    compose_forecast,
    inside_mask,
    pose_warp_forecast,
    warp_current,
)
from renderworld.world.movers import object_constant_velocity_forecast

from .test_movers import CAR, GRID, ROAD, VOX, S, _cells, _scene

TERRAIN = OCC3D_CLASSES.index("terrain")


def _straight_poses(step_voxels: float = 1.0) -> torch.Tensor:
    """[1, S, 3] the ego ``step_voxels`` further along x at each future step."""
    k = torch.arange(1, S + 1, dtype=torch.float64)
    return torch.stack([k * step_voxels * VOX, 0 * k, 0 * k], dim=-1)[None]


def test_static_warp_is_the_current_frame_along_the_poses():
    hist, poses = _scene()
    h, hp = torch.from_numpy(hist)[None], torch.from_numpy(poses)[None]
    fut = _straight_poses()
    out = warp_current(h, hp, fut, GRID, "static")
    assert torch.equal(out, warp_along_poses(h[:, -1], fut, GRID))


def test_object_cv_warp_moves_the_mover_and_leaves_the_parked_car():
    hist, poses = _scene(mover_step=(0, 1))
    h, hp = torch.from_numpy(hist)[None], torch.from_numpy(poses)[None]
    out = warp_current(h, hp, _straight_poses(), GRID, "object_cv")[0].numpy()
    for k in range(1, S + 1):
        assert _cells(out[k - 1], CAR) == {(20 - k, 10), (10 - k, 10 + k)}, k
    # Along the constant-turn-rate poses it is the object-CV baseline, voxel for voxel.
    from renderworld.world.baselines import constant_turn_rate_poses

    ctr = constant_turn_rate_poses(hp.double(), S)
    np.testing.assert_array_equal(
        warp_current(h, hp, ctr, GRID, "object_cv")[0].numpy(),
        object_constant_velocity_forecast(hist, poses, S, GRID),
    )


def test_unknown_movers_name_the_argument():
    hist, poses = _scene()
    with pytest.raises(ValueError, match="movers"):
        warp_current(torch.from_numpy(hist)[None], torch.from_numpy(poses)[None],
                     _straight_poses(), GRID, "flow")  # fmt: skip


def test_compose_takes_the_warp_inside_and_static_seen_classes_outside():
    cur = torch.full((1, *GRID.shape), FREE_ID, dtype=torch.uint8)
    cur[0, :, :, 0] = ROAD
    cur[0, 5, 5, 1] = CAR
    fut = _straight_poses(3.0)
    warped = warp_along_poses(cur, fut, GRID)
    inside = inside_mask(fut, GRID, cur.device)
    assert not inside[0, -1, -1].any() and inside[0, -1, 0].all()  # the far rows are new
    net = torch.full_like(warped, ROAD)
    net[..., 1] = CAR  # a decoder that fills revealed space with cars on the road
    net[0, :, -1, :, 0] = TERRAIN  # and terrain, which the current frame does not hold
    out = compose_forecast(cur, warped, inside, net)
    assert torch.equal(out[inside], warped[inside])
    outside = out[~inside]
    assert (outside[..., 0][outside[..., 0] != FREE_ID] == ROAD).all()
    assert (outside[..., 1] == FREE_ID).all()  # no car enters through revealed space
    assert not (out == TERRAIN).any()  # a class the current frame does not hold
    assert (outside[..., 0] == ROAD).any()  # the road continues into revealed space


class _IdentityCodec:
    """Codes = the frames themselves (one codebook on the full grid, z folded)."""

    def encode(self, aligned, warped):
        return aligned[:, :, None, :, :, 0].long(), warped[:, :, None, :, :, 0].long()

    def decode(self, codes):
        return codes[:, :, 0, ..., None].repeat(1, 1, 1, 1, GRID.shape[2])


class _RoadModel(torch.nn.Module):
    """Scores the road's code as the certain answer everywhere; records what it was given."""

    movers = "object_cv"

    def forward(self, tokens, sequence_poses, command):
        self.seen = (tokens.shape, sequence_poses.shape)
        h1 = tokens.shape[1] - S
        codes = torch.full_like(tokens[:, h1:, 0], ROAD)
        return [torch.nn.functional.one_hot(codes, 32).permute(0, 1, 4, 2, 3).float()]


def test_pose_warp_forecast_runs_the_four_steps_with_the_models_movers():
    hist, poses = _scene(mover_step=(0, 1))
    h, hp = torch.from_numpy(hist)[None], torch.from_numpy(poses)[None].float()
    fut = _straight_poses().float()
    model = _RoadModel()
    fc = pose_warp_forecast(model, h, hp, fut, torch.zeros(1, dtype=torch.long), GRID,
                            _IdentityCodec())  # fmt: skip
    # The token network reads the 4 aligned history frames, then the S warped ones.
    assert model.seen == ((1, len(hist) - 1 + S, 1, *GRID.shape[:2]), (1, len(hist) - 1 + S, 3))
    assert torch.equal(fc.warp, warp_current(h, hp, fut, GRID, "object_cv"))
    assert fc.forecast.shape == (1, S, *GRID.shape) and fc.forecast.dtype == torch.uint8
    inside = inside_mask(fut, GRID, h.device)
    assert (~inside).any()  # the ego moves: some space is newly revealed
    assert torch.equal(fc.forecast[inside], fc.warp[inside])
    assert (fc.net == ROAD).all()  # the decoded network forecast
    assert (fc.forecast[~inside] == ROAD).all()  # revealed space from the network, not the warp
