"""Ego trajectories and GT agent boxes in the current ego frame.

The driving command of a sample is :func:`renderworld.world.ego.command_from_trajectory` of its
GT future (one rule for the converter, the planner API and the metrics).

Planning quantities live in the **current ego frame** (docs/conventions.md#frames: origin rear axle,
x forward, y left). Frame ``k``'s position is the origin of its ego pose (``ego2global`` at its
LiDAR keyframe timestamp) expressed in the reference frame: ``(inv(E_ref) @ E_k)[:2, 3]``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from renderworld.constants import FUTURE_FRAMES
from renderworld.data.infos import BOX_FIELDS, HISTORY_STEPS
from renderworld.geometry import invert_pose

__all__ = [
    "relative_positions",
    "ego_history",
    "ego_future",
    "boxes_in_ego_frame",
]


def _check_poses(poses: np.ndarray, index: int) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses: expected [N, 4, 4] ego->global transforms, got {poses.shape}")
    if not 0 <= index < poses.shape[0]:
        raise ValueError(f"index: expected 0..{poses.shape[0] - 1}, got {index}")
    return poses


def relative_positions(reference: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Positions of ego frames in a reference ego frame.

    Args:
        reference: [4, 4] ego->global of the reference frame.
        poses: [N, 4, 4] ego->global of the frames.

    Returns:
        [N, 2] (x, y) metres in the reference ego frame.
    """
    rel = invert_pose(np.asarray(reference, dtype=np.float64)) @ np.asarray(poses, np.float64)
    return rel[:, :2, 3]


def ego_history(poses: np.ndarray, index: int, steps: int = HISTORY_STEPS):
    """Per-step past displacements of the ego, frames ``t-steps+1 .. t``.

    Entry ``j`` is the position of frame ``k = t - steps + 1 + j`` expressed in frame ``k-1``'s
    ego frame; it is valid when frame ``k-1`` exists in the scene.

    Args:
        poses: [N, 4, 4] ego->global of the scene's keyframes, in time order.
        index: t, the current keyframe's index.
        steps: number of displacements.

    Returns:
        ``(displacements [steps, 2] float64 metres (0 where invalid), mask [steps] bool)``.
    """
    poses = _check_poses(poses, index)
    disp = np.zeros((steps, 2))
    mask = np.zeros(steps, dtype=bool)
    for j in range(steps):
        k = index - steps + 1 + j
        if k - 1 >= 0:
            disp[j] = relative_positions(poses[k - 1], poses[k : k + 1])[0]
            mask[j] = True
    return disp, mask


def ego_future(poses: np.ndarray, index: int, steps: int = FUTURE_FRAMES):
    """Future ego positions ``t+1 .. t+steps`` in the current ego frame.

    Args:
        poses: [N, 4, 4] ego->global of the scene's keyframes, in time order.
        index: t.
        steps: number of future frames.

    Returns:
        ``(positions [steps, 2] float64 metres (0 past the scene end), mask [steps] bool)``.
    """
    poses = _check_poses(poses, index)
    pos = np.zeros((steps, 2))
    mask = np.zeros(steps, dtype=bool)
    future = poses[index + 1 : index + 1 + steps]
    if len(future):
        pos[: len(future)] = relative_positions(poses[index], future)
        mask[: len(future)] = True
    return pos, mask


def boxes_in_ego_frame(boxes: pd.DataFrame, ego_to_global: np.ndarray) -> np.ndarray:
    """Annotation boxes (global frame, from ``NuScenesReader.sample_boxes``) in an ego frame.

    Args:
        boxes: DataFrame with center_x, center_y, center_z, length, width, yaw, occ3d_class,
            instance_index.
        ego_to_global: [4, 4] ego->global of the target frame.

    Returns:
        [M, 7] float64 ``[x, y, length, width, yaw, occ3d_class, instance]``: centre (m) and
        heading (rad, relative to the ego x axis, in (-pi, pi]) in the target ego frame, the
        instance's index (the same road user has the same one in every frame).
    """
    n = len(boxes)
    out = np.zeros((n, len(BOX_FIELDS)))
    if n == 0:
        return out
    yaw = boxes["yaw"].to_numpy(np.float64)
    mats = np.zeros((n, 4, 4))
    mats[:, 0, 0] = np.cos(yaw)
    mats[:, 0, 1] = -np.sin(yaw)
    mats[:, 1, 0] = np.sin(yaw)
    mats[:, 1, 1] = np.cos(yaw)
    mats[:, 2, 2] = 1.0
    mats[:, 3, 3] = 1.0
    mats[:, 0, 3] = boxes["center_x"].to_numpy(np.float64)
    mats[:, 1, 3] = boxes["center_y"].to_numpy(np.float64)
    mats[:, 2, 3] = boxes["center_z"].to_numpy(np.float64)
    rel = invert_pose(np.asarray(ego_to_global, dtype=np.float64)) @ mats
    out[:, 0] = rel[:, 0, 3]
    out[:, 1] = rel[:, 1, 3]
    out[:, 2] = boxes["length"].to_numpy(np.float64)
    out[:, 3] = boxes["width"].to_numpy(np.float64)
    out[:, 4] = np.arctan2(rel[:, 1, 0], rel[:, 0, 0])
    out[:, 5] = boxes["occ3d_class"].to_numpy(np.float64)
    out[:, 6] = boxes["instance_index"].to_numpy(np.float64)
    return out
