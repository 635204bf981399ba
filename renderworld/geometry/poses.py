"""Rigid poses: 4x4 homogeneous transforms from nuScenes translation + quaternion.

Quaternions are ``[w, x, y, z]`` everywhere (nuScenes and transforms3d agree). A pose
``T_a_from_b`` maps points expressed in frame ``b`` into frame ``a``: ``p_a = T @ p_b``.
``calibrated_sensor`` records are sensor→ego and ``ego_pose`` records are ego→global.

Functions accept numpy arrays or torch tensors and return the same kind.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

import numpy as np
import transforms3d

__all__ = [
    "pose_matrix",
    "pose_to_translation_quaternion",
    "invert_pose",
    "compose",
    "transform_points",
    "yaw_of",
    "frame_poses_from_poses",
    "QUAT_EPS",
]

QUAT_EPS = 1e-12
ArrayT = TypeVar("ArrayT")


def _check_vec(name: str, value, length: int) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (length,):
        raise ValueError(f"{name}: expected {length} numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite numbers, got {arr.tolist()}")
    return arr


def pose_matrix(translation: Sequence[float], rotation: Sequence[float]) -> np.ndarray:
    """Build a 4x4 float64 transform from a translation and a ``[w, x, y, z]`` quaternion.

    Args:
        translation: [3] metres.
        rotation: [4] quaternion ``[w, x, y, z]``; normalised here (must not be zero).

    Returns:
        [4, 4] float64 homogeneous transform.

    Raises:
        ValueError: on wrong lengths, non-finite values or a zero quaternion.
    """
    t = _check_vec("translation", translation, 3)
    q = _check_vec("rotation", rotation, 4)
    norm = float(np.linalg.norm(q))
    if norm < 1e-8:
        raise ValueError(f"rotation: quaternion [w, x, y, z] has zero norm: {q.tolist()}")
    mat = np.eye(4, dtype=np.float64)
    mat[:3, :3] = transforms3d.quaternions.quat2mat(q / norm)
    mat[:3, 3] = t
    return mat


def pose_to_translation_quaternion(mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 4x4 rigid transform into translation [3] and quaternion ``[w, x, y, z]`` [4].

    The quaternion is returned with ``w >= 0``.
    """
    mat = np.asarray(mat, dtype=np.float64)
    if mat.shape != (4, 4):
        raise ValueError(f"mat: expected shape (4, 4), got {mat.shape}")
    q = transforms3d.quaternions.mat2quat(mat[:3, :3])
    if q[0] < 0:
        q = -q
    return mat[:3, 3].copy(), q


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def invert_pose(mat: ArrayT) -> ArrayT:
    """Invert rigid transforms ``[..., 4, 4]`` exactly (``R^T``, ``-R^T t``).

    Args:
        mat: [..., 4, 4] numpy array or torch tensor.

    Returns:
        [..., 4, 4] inverse, same type and dtype.
    """
    if mat.shape[-2:] != (4, 4):
        raise ValueError(f"mat: expected shape [..., 4, 4], got {tuple(mat.shape)}")
    rot = mat[..., :3, :3]
    trans = mat[..., :3, 3:]
    if _is_torch(mat):
        import torch

        rot_t = rot.transpose(-1, -2)
        out = torch.zeros_like(mat)
        out[..., :3, :3] = rot_t
        out[..., :3, 3:] = -rot_t @ trans
        out[..., 3, 3] = 1
        return out
    rot_t = np.swapaxes(rot, -1, -2)
    out = np.zeros_like(mat)
    out[..., :3, :3] = rot_t
    out[..., :3, 3:] = -rot_t @ trans
    out[..., 3, 3] = 1
    return out


def compose(*mats):
    """Compose transforms left to right as matrix products: ``compose(A, B) = A @ B``.

    ``compose(T_global_from_ego, T_ego_from_sensor)`` is sensor→global.
    """
    if not mats:
        raise ValueError("compose: expected at least one transform")
    out = mats[0]
    for m in mats[1:]:
        out = out @ m
    return out


def transform_points(mat, points):
    """Apply a 4x4 transform to points.

    Args:
        mat: [4, 4] (or [..., 4, 4] broadcastable against points' batch dims).
        points: [..., N, 3] points in the source frame.

    Returns:
        [..., N, 3] points in the target frame, same type as ``points``.
    """
    if points.shape[-1] != 3:
        raise ValueError(f"points: expected shape [..., N, 3], got {tuple(points.shape)}")
    rot = mat[..., :3, :3]
    trans = mat[..., :3, 3]
    if _is_torch(points):
        return (
            points @ rot.transpose(-1, -2).to(points.dtype) + trans.to(points.dtype)[..., None, :]
        )
    return points @ np.swapaxes(rot, -1, -2) + trans[..., None, :]


def yaw_of(mat) -> float | np.ndarray:
    """Heading (rad) of the x axis of rotation ``[..., 4, 4]`` or ``[..., 3, 3]`` about z."""
    return np.arctan2(np.asarray(mat)[..., 1, 0], np.asarray(mat)[..., 0, 0])


def _check_ego_poses(ego_to_global, current: int) -> np.ndarray:
    poses = np.asarray(ego_to_global, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) < 1:
        raise ValueError(f"ego_to_global: expected [T, 4, 4] poses, got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("ego_to_global: expected finite poses")
    if not isinstance(current, (int, np.integer)) or not 0 <= current < len(poses):
        raise ValueError(f"current: expected a frame index in [0, {len(poses)}), got {current!r}")
    return poses


def frame_poses_from_poses(ego_to_global, current: int) -> np.ndarray:
    """(x, y, yaw) of every ego frame in the current ego frame.

    Args:
        ego_to_global: [T, 4, 4] ego->global poses of frames 0..T-1 (nuScenes ``ego_pose``).
        current: index of the current frame t.

    Returns:
        [T, 3] float64: metres, metres, radians (row ``current`` is zeros). Usable as
        ``occupancy_poses`` of :class:`renderworld.metrics.PlanningMetric`; the sequence
        datasets' ``history_poses`` / ``future_poses`` are its rows.
    """
    poses = _check_ego_poses(ego_to_global, current)
    rel = invert_pose(poses[current]) @ poses  # frame k -> current frame
    return np.column_stack([rel[:, 0, 3], rel[:, 1, 3], yaw_of(rel)])
