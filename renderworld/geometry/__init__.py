"""Geometry: poses, cameras and voxel grids (frames and pixels: docs/conventions.md)."""

from renderworld.geometry.camera import (
    DEVKIT_MIN_DEPTH,
    lidar_to_camera_transform,
    map_lidar_to_image,
    project_points,
    scale_intrinsics,
)
from renderworld.geometry.poses import (
    compose,
    invert_pose,
    pose_matrix,
    pose_to_translation_quaternion,
    transform_points,
    yaw_of,
)
from renderworld.geometry.voxel import VoxelGrid

__all__ = [
    "DEVKIT_MIN_DEPTH",
    "VoxelGrid",
    "compose",
    "invert_pose",
    "lidar_to_camera_transform",
    "map_lidar_to_image",
    "pose_matrix",
    "pose_to_translation_quaternion",
    "project_points",
    "scale_intrinsics",
    "transform_points",
    "yaw_of",
]
