import math

import numpy as np
import pytest

from renderworld.geometry import pose_matrix
from renderworld.world.ego import (
    command_from_trajectory,
    displacements_from_poses,
    frame_poses_from_poses,
)


def yaw_pose(x, y, yaw):
    return pose_matrix([x, y, 0.0], [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def test_straight_drive_heading_north_is_forward_in_the_ego_frame():
    # Global heading +y (yaw 90 deg), 5 m per keyframe: in the ego frame that is +x.
    poses = np.stack([yaw_pose(10.0, 5.0 * k, math.pi / 2) for k in range(5)])
    d = displacements_from_poses(poses, current=4)
    np.testing.assert_allclose(d, np.tile([5.0, 0.0], (4, 1)), atol=1e-9)
    fp = frame_poses_from_poses(poses, current=4)
    np.testing.assert_allclose(fp[4], 0.0, atol=1e-12)
    np.testing.assert_allclose(fp[0], [-20.0, 0.0, 0.0], atol=1e-9)


def test_turn_left_quarter_circle_and_future_cumsum():
    # Quarter circle of radius 10 m turning left, heading tangent to the circle.
    angles = np.linspace(0, math.pi / 2, 7)
    poses = np.stack([yaw_pose(10 * math.sin(a), 10 - 10 * math.cos(a), a) for a in angles])
    fp = frame_poses_from_poses(poses, current=0)
    np.testing.assert_allclose(fp[-1], [10.0, 10.0, math.pi / 2], atol=1e-9)
    d = displacements_from_poses(poses, current=0)
    np.testing.assert_allclose(np.cumsum(d, 0), fp[1:, :2], atol=1e-9)  # trajectory = cumsum
    assert command_from_trajectory(np.cumsum(d, 0)) == "left"
    # Seen from the last frame, the earlier frames are behind and to the right.
    back = frame_poses_from_poses(poses, current=6)
    np.testing.assert_allclose(back[0, :2], [-10.0, 10.0], atol=1e-9)


@pytest.mark.parametrize(
    "y, cmd", [(2.0, "left"), (1.99, "straight"), (-1.99, "straight"), (-2.0, "right")]
)
def test_command_thresholds(y, cmd):
    traj = np.zeros((6, 2))
    traj[-1] = [10.0, y]
    assert command_from_trajectory(traj) == cmd


def test_ego_validation():
    with pytest.raises(ValueError, match=r"ego_to_global: expected \[T, 4, 4\]"):
        displacements_from_poses(np.eye(4), current=0)
    with pytest.raises(ValueError, match="current: expected a frame index"):
        displacements_from_poses(np.stack([np.eye(4)] * 3), current=3)
    with pytest.raises(ValueError, match="future_positions: expected finite"):
        command_from_trajectory(np.array([[0.0, np.nan]]))
