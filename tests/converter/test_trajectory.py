"""Ego history/future, commands and boxes in the current ego frame (infos and unit cases)."""

import numpy as np
import pandas as pd
import pytest

from data_converters import boxes_in_ego_frame, ego_future, ego_history
from renderworld.data import load_infos
from renderworld.data.infos import stack_column
from renderworld.geometry import pose_matrix
from renderworld.world.ego import command_from_trajectory
from tests.converter.datasets_for_tests import build_and_convert
from tests.data.builder import ego_pose_at


def gt_in_frame(path, t_now, t_other):
    """Position of the ego at time t_other in the ego frame at t_now (planar, analytic)."""
    (x0, y0, _), q0 = ego_pose_at(path, t_now)
    (x1, y1, _), _ = ego_pose_at(path, t_other)
    yaw = 2 * np.arctan2(q0[3], q0[0])
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = x1 - x0, y1 - y0
    return np.array([c * dx + s * dy, -s * dx + c * dy])


@pytest.fixture(scope="module")
def turns(tmp_path_factory):
    out = {}
    for path in ("straight", "right"):
        root = tmp_path_factory.mktemp(path) / "ds"
        out[path] = load_infos(build_and_convert(root, ego_path=path, num_points=200), "train")
    return out


def test_left_turn_future_matches_ground_truth_and_commands_left(left_turn):
    infos = load_infos(left_turn[1], "train")
    assert len(infos) == 8
    for i, row in infos.iterrows():
        fut = np.asarray(row["ego_future"]).reshape(6, 2)
        mask = np.asarray(row["ego_future_mask"])
        n_valid = min(6, 7 - i)
        assert mask.tolist() == [True] * n_valid + [False] * (6 - n_valid)
        for k in range(n_valid):
            np.testing.assert_allclose(
                fut[k], gt_in_frame("left", 0.5 * i, 0.5 * (i + k + 1)), atol=0.01
            )
        assert (fut[n_valid:] == 0).all()
    # A 20 m radius turn at 10 m/s: 3 s ahead is far to the left.
    assert infos["command"].tolist()[:6] == ["left"] * 6
    assert infos["command"].iloc[7] == "straight"  # the scene's last frame has no future


def test_history_is_per_step_displacement_with_mask(left_turn):
    infos = load_infos(left_turn[1], "train")
    for i, row in infos.iterrows():
        hist = np.asarray(row["ego_history"]).reshape(4, 2)
        mask = np.asarray(row["ego_history_mask"])
        for j in range(4):
            k = i - 3 + j  # frame k expressed in frame k-1's ego frame
            assert mask[j] == (k - 1 >= 0)
            if mask[j]:
                np.testing.assert_allclose(
                    hist[j], gt_in_frame("left", 0.5 * (k - 1), 0.5 * k), atol=0.01
                )
            else:
                assert (hist[j] == 0).all()


def test_straight_and_right(turns):
    straight = turns["straight"]
    assert set(straight["command"]) == {"straight"}
    fut = stack_column(straight, "ego_future", (6, 2))
    np.testing.assert_allclose(fut[0], [[5.0 * (k + 1), 0.0] for k in range(6)], atol=1e-6)
    right = turns["right"]
    assert right["command"].tolist()[:6] == ["right"] * 6


def test_command_thresholds_and_scene_end_rule():
    mask = np.ones(6, bool)
    fut = np.zeros((6, 2))
    for y, cmd in ((2.0, "left"), (1.999, "straight"), (-2.0, "right"), (-1.999, "straight")):
        fut[5, 1] = y
        assert command_from_trajectory(fut, mask) == cmd
    # Past the scene end the last valid point decides: y at step 3 is 2.5 m.
    fut = np.array([[1, 0.5], [2, 1.5], [3, 2.5], [0, 0], [0, 0], [0, 0]], float)
    assert command_from_trajectory(fut, np.array([1, 1, 1, 0, 0, 0], bool)) == "left"
    assert command_from_trajectory(fut, np.zeros(6, bool)) == "straight"
    with pytest.raises(ValueError, match=r"future_positions: expected finite \[S, 2\]"):
        command_from_trajectory(np.zeros((6, 3)), mask)


def test_history_and_future_unit_cases():
    poses = np.stack([pose_matrix([2.0 * i, 0, 0], [1, 0, 0, 0]) for i in range(3)])
    fut, mask = ego_future(poses, 1)
    assert mask.tolist() == [True] + [False] * 5
    np.testing.assert_allclose(fut[0], [2.0, 0.0])
    hist, hmask = ego_history(poses, 2)
    assert hmask.tolist() == [False, False, True, True]
    np.testing.assert_allclose(hist[2:], [[2.0, 0.0], [2.0, 0.0]])
    with pytest.raises(ValueError, match=r"index: expected 0..2, got 3"):
        ego_future(poses, 3)
    with pytest.raises(ValueError, match=r"poses: expected \[N, 4, 4\]"):
        ego_history(np.eye(4), 0)


def test_boxes_in_ego_frame_hand_case():
    # Ego at (10, 5) heading +90 deg (facing +y). A box 3 m ahead of it, heading +x globally:
    # in the ego frame it sits at (3, 0) with yaw -90 deg.
    ego = pose_matrix([10.0, 5.0, 0.0], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    boxes = pd.DataFrame(
        {
            "center_x": [10.0],
            "center_y": [8.0],
            "center_z": [1.0],
            "length": [4.5],
            "width": [1.9],
            "yaw": [0.0],
            "occ3d_class": [4],
            "instance_index": [7],
        }
    )
    out = boxes_in_ego_frame(boxes, ego)
    np.testing.assert_allclose(out, [[3.0, 0.0, 4.5, 1.9, -np.pi / 2, 4.0, 7.0]], atol=1e-12)
    assert boxes_in_ego_frame(boxes.iloc[:0], ego).shape == (0, 7)


def test_future_boxes_in_infos_are_in_the_current_ego_frame(left_turn):
    infos = load_infos(left_turn[1], "train")
    row = infos.iloc[2]
    frames = row["future_boxes"]
    assert len(frames) == 7
    assert [len(f) for f in frames] == [1, 1, 1, 1, 1, 1, 0]  # frame 8 is past the scene end
    (x0, y0, _), q0 = ego_pose_at("left", 1.0)
    yaw0 = 2 * np.arctan2(q0[3], q0[0])
    for k, f in enumerate(frames[:6]):
        # Builder box of keyframe i: centre (110 + 5 i, 52), yaw 0.5, length 4.5, width 1.9.
        i = 2 + k
        dx, dy = 110.0 + 5 * i - x0, 52.0 - y0
        c, s = np.cos(yaw0), np.sin(yaw0)
        expect = [c * dx + s * dy, -s * dx + c * dy, 4.5, 1.9, 0.5 - yaw0, 4.0, 0.0]
        np.testing.assert_allclose(np.asarray(f[0]), expect, atol=1e-9)
