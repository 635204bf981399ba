"""Free-space targets of the back-projection: voxels in front of, at and behind a LiDAR depth."""

from __future__ import annotations

import pytest
import torch

from renderworld.img2occ.backproject import free_space_targets


def _camera_looking_along_x():
    # Camera at the ego origin looking along +x (camera z = ego x, camera x = -ego y,
    # camera y = -ego z); 4x4 depth map, focal 2 px, principal point at the centre.
    cam_to_ego = torch.eye(4)
    cam_to_ego[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    k = torch.tensor([[2.0, 0.0, 2.0], [0.0, 2.0, 2.0], [0.0, 0.0, 1.0]])
    return cam_to_ego[None, None], k[None, None]


def test_voxels_in_front_of_the_lidar_depth_are_free_and_at_it_are_not():
    cam_to_ego, k = _camera_looking_along_x()
    depth = torch.zeros(1, 1, 4, 4)
    depth[0, 0, 2, 2] = 10.0  # the pixel that the optical axis (+x) falls into
    # Voxel centres on the axis at x = 3, 8.5, 10, 11, 20 m, one beside it (off the depth
    # map's labelled pixel) and one behind the camera.
    centres = torch.tensor(
        [[3.0, 0, 0], [8.5, 0, 0], [10.0, 0, 0], [11.0, 0, 0], [20.0, 0, 0], [3.0, 2.5, 0],
         [-3.0, 0, 0]]
    )  # fmt: skip
    free = free_space_targets(centres, cam_to_ego, k, depth, margin=1.0)
    assert free.tolist() == [[True, True, False, False, False, False, False]]
    # A wider margin keeps the voxel at 8.5 m (within 1.6 m of the surface) out of it.
    free = free_space_targets(centres, cam_to_ego, k, depth, margin=1.6)
    assert free.tolist() == [[True, False, False, False, False, False, False]]


def test_a_voxel_seen_at_a_surface_by_another_camera_is_not_free():
    cam_to_ego, k = _camera_looking_along_x()
    two = cam_to_ego.repeat(1, 2, 1, 1)
    depth = torch.zeros(1, 2, 4, 4)
    depth[0, 0, 2, 2] = 10.0  # camera 0: empty up to 10 m
    depth[0, 1, 2, 2] = 3.2  # camera 1 (same pose): a surface at 3.2 m
    centres = torch.tensor([[3.0, 0.0, 0.0]])
    assert free_space_targets(centres, two, k.repeat(1, 2, 1, 1), depth, 1.0).tolist() == [[False]]


def test_validation_names_the_argument():
    cam_to_ego, k = _camera_looking_along_x()
    with pytest.raises(ValueError, match="margin"):
        free_space_targets(torch.zeros(1, 3), cam_to_ego, k, torch.zeros(1, 1, 4, 4), 0.0)
    with pytest.raises(ValueError, match="cam_to_ego"):
        free_space_targets(torch.zeros(1, 3), cam_to_ego, k, torch.zeros(1, 2, 4, 4), 1.0)
