"""The Camera setting in closed loop: cameras rendered at the ego's pose, read out by Img2Occ."""

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, get_grid
from renderworld.img2occ import Img2Occ, Img2OccConfig
from renderworld.sim import build_worlds
from renderworld.sim.closed_loop.cameras import CameraObserver
from renderworld.sim.closed_loop.observe import pose_matrix_2d
from tools.make_fixtures import config_from_preset


def tiny_img2occ(grid="coarse") -> Img2Occ:
    torch.manual_seed(0)
    cfg = Img2OccConfig(grid=grid, input_size=(48, 88), render_size=(18, 32),
                        encoder_channels=(8, 16, 16), feature_channels=16, head_channels=32,
                        head_blocks=1)  # fmt: skip
    return Img2Occ(cfg).eval()


@pytest.fixture(scope="module")
def world():
    return build_worlds(config_from_preset("interactions", num_scenes=1))[0]


def test_the_cameras_are_rendered_at_the_pose_and_read_out_on_the_planner_grid(world):
    grid = get_grid("coarse")
    obs = CameraObserver(tiny_img2occ(), grid, (88, 48))
    (xy, yaw) = world.ego.trajectory.pose(2.0)
    pose = pose_matrix_2d(xy[0], xy[1], float(yaw))
    images = obs.images(world, 2.0, pose)
    assert images.shape == (1, 6, 3, 48, 88) and 0 <= float(images.min()) < float(images.max()) <= 1
    moved = obs.images(world, 2.0, pose_matrix_2d(xy[0] + 15.0, xy[1], float(yaw)))
    assert not torch.equal(images, moved)  # another pose sees another scene
    occ = obs.render(world, 2.0, pose)
    assert occ.shape == tuple(grid.shape) and occ.dtype == np.uint8 and occ.max() <= FREE_ID
    np.testing.assert_array_equal(occ, obs.render(world, 2.0, pose))  # deterministic
    # A planner grid coarser than Img2Occ's is down-sampled; another range is refused.
    coarse_obs = CameraObserver(tiny_img2occ("half"), grid, (88, 48))
    assert coarse_obs.factor == (2, 2, 2)
    assert coarse_obs.render(world, 2.0, pose).shape == (50, 50, 4)
    with pytest.raises(ValueError, match="grid: the planner's grid"):
        CameraObserver(tiny_img2occ("coarse"), get_grid("half"), (88, 48))
