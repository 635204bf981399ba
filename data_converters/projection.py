"""LiDAR -> camera label maps: the devkit transform chain, a z-buffer, the label-resolution rule.

Each point goes lidar -> ego (its calibrated_sensor) -> global (the ego pose at *its own* sweep
time) -> ego (the ego pose at the camera's time) -> camera (camera calibrated_sensor, inverted),
exactly the devkit's ``map_pointcloud_to_image`` chain; so sweeps and neighbouring keyframes are
motion compensated through their own ego poses. Points with camera depth > ``min_depth`` that
land in the stored image ``[0, W) x [0, H)`` label pixel ``(floor(u * sx), floor(v * sy))`` of
the label map (``sx = W_label / W``, ``sy = H_label / H``; docs/conventions.md#pixels), and the
nearest point per pixel wins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import OCC3D_CLASSES
from renderworld.data.labels2d import IGNORE_LABEL, SparseLabels2D, zbuffer_nearest
from renderworld.geometry import DEVKIT_MIN_DEPTH, lidar_to_camera_transform, map_lidar_to_image

__all__ = [
    "STATIC_CLASS_IDS",
    "PointSource",
    "CameraView",
    "project_to_label_map",
    "label_maps",
    "label_size_for",
    "unlabelled",
]

#: Occ3D classes whose points neighbouring keyframes may contribute (they do not move).
STATIC_CLASS_IDS: tuple[int, ...] = tuple(
    OCC3D_CLASSES.index(n)
    for n in ("driveable_surface", "other_flat", "sidewalk", "terrain", "manmade", "vegetation")
)


@dataclass(frozen=True)
class PointSource:
    """A LiDAR sweep with its pose.

    Attributes:
        points: [N, 3] points in the LiDAR frame (metres).
        labels: [N] uint8 Occ3D ids, or ``IGNORE_LABEL`` for points without semantics.
        lidar_to_ego: [4, 4] LiDAR calibrated_sensor.
        ego_to_global: [4, 4] ego pose at the sweep's timestamp.
    """

    points: np.ndarray
    labels: np.ndarray
    lidar_to_ego: np.ndarray
    ego_to_global: np.ndarray


@dataclass(frozen=True)
class CameraView:
    """A camera at its own timestamp.

    Attributes:
        K: [3, 3] intrinsics at the stored image size (pixels).
        sensor_to_ego: [4, 4] camera calibrated_sensor.
        ego_to_global: [4, 4] ego pose at the camera's timestamp.
        image_size: (H, W) of the stored image (pixels).
        label_size: (H_label, W_label) of the label map (pixels).
    """

    K: np.ndarray
    sensor_to_ego: np.ndarray
    ego_to_global: np.ndarray
    image_size: tuple[int, int]
    label_size: tuple[int, int]


def label_size_for(image_size: tuple[int, int], scale: float | None, size=None) -> tuple[int, int]:
    """Label-map (H, W) for an image: explicit ``size`` or ``round(scale * (H, W))``.

    Raises:
        ValueError: if neither or both are given, or the result is empty.
    """
    if (scale is None) == (size is None):
        raise ValueError(f"label scale/size: give exactly one, got scale={scale}, size={size}")
    if size is not None:
        h, w = (int(x) for x in size)
    else:
        if not scale > 0:
            raise ValueError(f"label scale: expected > 0, got {scale}")
        h, w = round(image_size[0] * scale), round(image_size[1] * scale)
    if h <= 0 or w <= 0 or h > 65535 or w > 65535:
        raise ValueError(f"label size: expected 1..65535 pixels per side, got {h}x{w}")
    return h, w


def project_to_label_map(
    points_lidar: np.ndarray,
    labels: np.ndarray,
    lidar_to_camera: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    label_size: tuple[int, int],
    min_depth: float = DEVKIT_MIN_DEPTH,
) -> SparseLabels2D:
    """Project labelled points into one camera and keep the nearest per label pixel.

    Args:
        points_lidar: [N, 3] points in the LiDAR frame (metres).
        labels: [N] uint8 per-point labels.
        lidar_to_camera: [4, 4] (see ``renderworld.geometry.lidar_to_camera_transform``).
        K: [3, 3] intrinsics at the stored image size.
        image_size: (H, W) stored image size.
        label_size: (H_label, W_label).
        min_depth: keep camera depth > ``min_depth`` metres.

    Returns:
        :class:`SparseLabels2D` sorted by pixel (row-major).
    """
    parts = [(points_lidar, labels, lidar_to_camera)]
    return _project_many(parts, K, image_size, label_size, min_depth)


def _project_many(parts, K, image_size, label_size, min_depth) -> SparseLabels2D:
    h, w = (int(x) for x in image_size)
    lh, lw = (int(x) for x in label_size)
    sx, sy = lw / w, lh / h
    us, vs, ds, ls = [], [], [], []
    for points, labels, l2c in parts:
        labels = np.asarray(labels)
        if labels.shape != (len(points),):
            raise ValueError(f"labels: expected [{len(points)}], got {labels.shape}")
        uv, depth, index = map_lidar_to_image(
            points, l2c, K, w, h, min_depth=min_depth, devkit_border=False
        )
        us.append(np.minimum(np.floor(uv[:, 0] * sx), lw - 1).astype(np.int64))
        vs.append(np.minimum(np.floor(uv[:, 1] * sy), lh - 1).astype(np.int64))
        ds.append(depth)
        ls.append(labels[index])
    u, v, d, lab = (np.concatenate(x) for x in (us, vs, ds, ls))
    keep = zbuffer_nearest(v * lw + u, d)
    return SparseLabels2D(
        u[keep].astype(np.uint16),
        v[keep].astype(np.uint16),
        d[keep].astype(np.float32),
        lab[keep].astype(np.uint8),
        lh,
        lw,
    )


def label_maps(
    sources: list[PointSource], cameras: list[CameraView], min_depth: float = DEVKIT_MIN_DEPTH
) -> list[SparseLabels2D]:
    """Sparse label maps of several cameras from several (motion-compensated) point sources.

    Args:
        sources: keyframe sweep first, then optional sweeps / neighbouring keyframes.
        cameras: the views to label.
        min_depth: metres.

    Returns:
        [len(cameras)] sparse label maps (one z-buffer over all sources per camera).
    """
    out = []
    for cam in cameras:
        parts = [
            (
                src.points,
                src.labels,
                lidar_to_camera_transform(
                    src.lidar_to_ego, src.ego_to_global, cam.ego_to_global, cam.sensor_to_ego
                ),
            )
            for src in sources
        ]
        out.append(_project_many(parts, cam.K, cam.image_size, cam.label_size, min_depth))
    return out


def unlabelled(n: int) -> np.ndarray:
    """[n] uint8 of ``IGNORE_LABEL`` (points without semantics)."""
    return np.full(n, IGNORE_LABEL, dtype=np.uint8)
