import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from renderworld.geometry import (
    invert_pose,
    lidar_to_camera_transform,
    map_lidar_to_image,
    pose_matrix,
    project_points,
    scale_intrinsics,
    transform_points,
)

# Vehicle n015's calibration (docs/formats.md#sensors-and-calibration), 1600x900.
CAM_FRONT_T = [1.7008, 0.0160, 1.5110]
CAM_FRONT_Q = [0.49980, -0.50303, 0.49978, -0.49737]
LIDAR_T = [0.9437, 0.0, 1.8402]
LIDAR_Q = [0.70780, -0.00649, 0.01065, -0.70631]
K_FRONT = np.array([[1266.4, 0, 816.3], [0, 1266.4, 491.5], [0, 0, 1]])


def test_ideal_front_camera_hand_computed():
    # Ideal CAM_FRONT rotation: camera z -> ego x, camera x -> ego -y, camera y -> ego -z.
    cam2ego = pose_matrix(CAM_FRONT_T, [0.5, -0.5, 0.5, -0.5])
    np.testing.assert_allclose(cam2ego[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    # 10 m ahead of the camera and 1 m to its right (ego -y): camera (1, 0, 10).
    p_ego = np.array([[1.7008 + 10.0, 0.0160 - 1.0, 1.5110]])
    p_cam = transform_points(invert_pose(cam2ego), p_ego)
    np.testing.assert_allclose(p_cam, [[1.0, 0.0, 10.0]], atol=1e-12)
    uv, depth, valid = project_points(p_cam, K_FRONT)
    np.testing.assert_allclose(uv, [[816.3 + 126.64, 491.5]])
    assert depth[0] == pytest.approx(10.0) and valid[0]


def test_real_front_camera_point_ahead_lands_near_principal_point():
    cam2ego = pose_matrix(CAM_FRONT_T, CAM_FRONT_Q)
    p_ego = np.array([[1.7008 + 10.0, 0.0160, 1.5110]])
    uv, depth, valid = project_points(transform_points(invert_pose(cam2ego), p_ego), K_FRONT)
    assert valid[0] and depth[0] == pytest.approx(10.0, abs=1e-3)
    # The real rotation is within ~0.5 deg of ideal: < 15 px from (cx, cy) at fx=1266.
    assert np.abs(uv[0] - [816.3, 491.5]).max() < 15


def test_near_plane_masking_keeps_values_finite():
    pts = np.array([[0.0, 0.0, 5.0], [1.0, 1.0, 0.0], [1.0, 1.0, -3.0]])
    uv, depth, valid = project_points(pts, K_FRONT, near=0.1)
    assert valid.tolist() == [True, False, False]
    assert np.isfinite(uv).all()
    uv_t, _, valid_t = project_points(torch.tensor(pts), torch.tensor(K_FRONT), near=0.1)
    np.testing.assert_allclose(uv_t.numpy(), uv)
    assert valid_t.tolist() == valid.tolist()


@settings(max_examples=40, deadline=None)
@given(
    s=st.floats(0.05, 4.0),
    x=st.floats(-5, 5),
    y=st.floats(-3, 3),
    z=st.floats(2, 60),
)
def test_resized_intrinsics_keep_relative_pixel(s, x, y, z):
    pts = np.array([[x, y, z]])
    uv, _, _ = project_points(pts, K_FRONT)
    uv_s, _, _ = project_points(pts, scale_intrinsics(K_FRONT, s))
    np.testing.assert_allclose(uv_s / s, uv, rtol=1e-9, atol=1e-9)


def test_scale_intrinsics_rejects_non_positive():
    with pytest.raises(ValueError, match="scale: expected positive"):
        scale_intrinsics(K_FRONT, 0.0)


def test_lidar_to_camera_chain_across_timestamps():
    lidar2ego = pose_matrix(LIDAR_T, LIDAR_Q)
    cam2ego = pose_matrix(CAM_FRONT_T, CAM_FRONT_Q)
    ego_at_lidar = pose_matrix([100.0, 50.0, 0.0], [1, 0, 0, 0])
    # The ego moved 0.5 m forward between the LiDAR and the camera timestamps.
    ego_at_cam = pose_matrix([100.5, 50.0, 0.0], [1, 0, 0, 0])
    l2c = lidar_to_camera_transform(lidar2ego, ego_at_lidar, ego_at_cam, cam2ego)
    p_global = np.array([[115.0, 50.3, 1.2]])
    p_lidar = transform_points(invert_pose(ego_at_lidar @ lidar2ego), p_global)
    expected_cam = transform_points(invert_pose(ego_at_cam @ cam2ego), p_global)
    np.testing.assert_allclose(transform_points(l2c, p_lidar), expected_cam, atol=1e-9)


def test_map_lidar_to_image_filters_like_devkit():
    l2c = np.eye(4)
    pts = np.array(
        [
            [0.0, 0.0, 10.0],  # centre: kept
            [0.0, 0.0, 0.9],  # closer than 1 m: dropped
            [0.0, 0.0, -5.0],  # behind: dropped
            [-816.3 / 1266.4 * 10 + 0.5 / 1266.4 * 10, 0.0, 10.0],  # u = 0.5 < 1: dropped
        ]
    )
    uv, depth, idx = map_lidar_to_image(pts, l2c, K_FRONT, 1600, 900)
    assert idx.tolist() == [0]
    np.testing.assert_allclose(uv, [[816.3, 491.5]])
    np.testing.assert_allclose(depth, [10.0])
    _, _, idx2 = map_lidar_to_image(pts, l2c, K_FRONT, 1600, 900, devkit_border=False)
    assert idx2.tolist() == [0, 3]
    with pytest.raises(ValueError, match="points_lidar"):
        map_lidar_to_image(np.zeros((3, 2)), l2c, K_FRONT, 1600, 900)
