"""Pinhole cameras: projection with near-plane masking and the devkit LiDAR→image chain.

Camera frame: z forward, x right, y down. Pixel convention (docs/conventions.md#pixels):
pixel (i, j) (column, row) covers [i, i+1) x [j, j+1); a point projected to (u, v) labels pixel
(floor(u), floor(v)). Resizing an image by s scales fx, fy, cx, cy by s.
"""

from __future__ import annotations

import numpy as np

from renderworld.geometry.poses import compose, invert_pose, transform_points

__all__ = [
    "project_points",
    "scale_intrinsics",
    "lidar_to_camera_transform",
    "map_lidar_to_image",
    "DEVKIT_MIN_DEPTH",
]

#: The devkit's ``map_pointcloud_to_image`` keeps points with camera depth > 1 m.
DEVKIT_MIN_DEPTH = 1.0


def project_points(points_cam, K, near: float = 1e-3):
    """Project camera-frame points through intrinsics ``K``.

    Args:
        points_cam: [..., N, 3] points in the camera frame (metres).
        K: [..., 3, 3] intrinsics (pixels).
        near: points with camera z <= ``near`` (metres) are marked invalid; their pixel
            coordinates are computed with z clamped to ``near`` so they stay finite.

    Returns:
        Tuple ``(uv [..., N, 2] pixels, depth [..., N] metres (camera z), valid [..., N] bool)``,
        numpy or torch like ``points_cam``.
    """
    if points_cam.shape[-1] != 3:
        raise ValueError(f"points_cam: expected shape [..., N, 3], got {tuple(points_cam.shape)}")
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"K: expected shape [..., 3, 3], got {tuple(K.shape)}")
    depth = points_cam[..., 2]
    valid = depth > near
    if type(points_cam).__module__.startswith("torch"):
        z = depth.clamp_min(near)
        K = K.to(points_cam.dtype)
    else:
        z = np.maximum(depth, near)
    x = points_cam[..., 0] / z
    y = points_cam[..., 1] / z
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]
    cx, cy = K[..., 0, 2, None], K[..., 1, 2, None]
    skew = K[..., 0, 1, None]
    u = fx * x + skew * y + cx
    v = fy * y + cy
    if type(points_cam).__module__.startswith("torch"):
        import torch

        uv = torch.stack([u, v], dim=-1)
    else:
        uv = np.stack([u, v], axis=-1)
    return uv, depth, valid


def scale_intrinsics(K, sx: float, sy: float | None = None):
    """Scale intrinsics for an image resized by ``sx`` horizontally and ``sy`` vertically.

    With the pixel-area convention (centre of pixel i at i + 0.5) resizing by s maps
    u -> s * u exactly, so fx, cx scale by sx and fy, cy by sy.

    Args:
        K: [..., 3, 3] intrinsics.
        sx: horizontal scale (new_width / old_width), > 0.
        sy: vertical scale; defaults to ``sx``.

    Returns:
        [..., 3, 3] scaled copy.
    """
    sy = sx if sy is None else sy
    if not (sx > 0 and sy > 0):
        raise ValueError(f"scale: expected positive scales, got sx={sx}, sy={sy}")
    out = K.clone() if hasattr(K, "clone") else np.array(K, dtype=np.float64, copy=True)
    out[..., 0, :] = out[..., 0, :] * sx
    out[..., 1, :] = out[..., 1, :] * sy
    return out


def lidar_to_camera_transform(
    lidar_to_ego: np.ndarray,
    ego_to_global_at_lidar: np.ndarray,
    ego_to_global_at_camera: np.ndarray,
    camera_to_ego: np.ndarray,
) -> np.ndarray:
    """The devkit's LiDAR→camera chain across two timestamps.

    lidar → ego (lidar calib) → global (ego pose at the LiDAR time) → ego (ego pose at
    the camera time, inverted) → camera (camera calib, inverted).

    Args:
        lidar_to_ego: [4, 4] LiDAR calibrated_sensor.
        ego_to_global_at_lidar: [4, 4] ego_pose at the LiDAR sample_data's timestamp.
        ego_to_global_at_camera: [4, 4] ego_pose at the camera sample_data's timestamp.
        camera_to_ego: [4, 4] camera calibrated_sensor.

    Returns:
        [4, 4] float64 transform, LiDAR frame → camera frame.
    """
    return compose(
        invert_pose(np.asarray(camera_to_ego, dtype=np.float64)),
        invert_pose(np.asarray(ego_to_global_at_camera, dtype=np.float64)),
        np.asarray(ego_to_global_at_lidar, dtype=np.float64),
        np.asarray(lidar_to_ego, dtype=np.float64),
    )


def map_lidar_to_image(
    points_lidar: np.ndarray,
    lidar_to_camera: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    min_depth: float = DEVKIT_MIN_DEPTH,
    devkit_border: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project LiDAR points into an image like the devkit's ``map_pointcloud_to_image``.

    Args:
        points_lidar: [N, 3] (or [N, >=3], extra columns ignored) points, LiDAR frame.
        lidar_to_camera: [4, 4] from :func:`lidar_to_camera_transform`.
        K: [3, 3] intrinsics of the image (pixels).
        width: image width (pixels).
        height: image height (pixels).
        min_depth: keep points with camera depth > ``min_depth`` metres.
        devkit_border: if True keep ``1 < u < W - 1`` and ``1 < v < H - 1`` as the devkit
            does; if False keep every point inside ``[0, W) x [0, H)``.

    Returns:
        ``(uv [M, 2] float64 pixels, depth [M] metres, index [M] int64 into points_lidar)``.
    """
    pts = np.asarray(points_lidar, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points_lidar: expected shape [N, >=3], got {pts.shape}")
    if width <= 0 or height <= 0:
        raise ValueError(f"width/height: expected positive sizes, got {width}x{height}")
    cam = transform_points(np.asarray(lidar_to_camera, dtype=np.float64), pts[:, :3])
    uv, depth, _ = project_points(cam, np.asarray(K, dtype=np.float64), near=1e-6)
    keep = depth > min_depth
    if devkit_border:
        keep &= (uv[:, 0] > 1) & (uv[:, 0] < width - 1) & (uv[:, 1] > 1) & (uv[:, 1] < height - 1)
    else:
        keep &= (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    index = np.nonzero(keep)[0]
    return uv[index], depth[index], index
