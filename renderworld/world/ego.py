"""Ego-motion quantities from ego poses, in the world model's conventions.

These pin the displacement/trajectory convention in code (see :mod:`renderworld.world.config`)
so datasets, the planner API and the metrics compute it the same way:

* positions ``p[k]`` = origin of ego frame k (rear axle; docs/conventions.md#frames - VAD uses the
  LiDAR origin instead, which differs by centimetres while turning) expressed in the **current** ego
  frame (x forward, y left), metres;
* ``d[i] = p[i + 1] - p[i]`` (VAD's per-step offsets); the future trajectory is
  ``p[t + 1 .. t + S]`` = cumulative sum of the future ``d``;
* the command follows docs/conventions.md#ego-motion-and-the-command from the lateral offset of the
  last future waypoint (3 s).
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import COMMAND_LATERAL_THRESHOLD
from renderworld.geometry.poses import invert_pose, yaw_of

__all__ = ["command_from_trajectory", "displacements_from_poses", "frame_poses_from_poses"]


def _check_poses(ego_to_global, current: int) -> np.ndarray:
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
        ``occupancy_poses`` of :class:`renderworld.metrics.PlanningMetric`.
    """
    poses = _check_poses(ego_to_global, current)
    rel = invert_pose(poses[current]) @ poses  # frame k -> current frame
    return np.column_stack([rel[:, 0, 3], rel[:, 1, 3], yaw_of(rel)])


def displacements_from_poses(ego_to_global, current: int) -> np.ndarray:
    """Per-step displacements ``d[i] = p[i+1] - p[i]`` in the current ego frame.

    Args:
        ego_to_global: [T, 4, 4] ego->global poses of consecutive keyframes.
        current: index of the current frame t (the frame the displacements are expressed in).

    Returns:
        [T-1, 2] float64 metres.
    """
    xy = frame_poses_from_poses(ego_to_global, current)[:, :2]
    return np.diff(xy, axis=0)


def command_from_trajectory(future_positions) -> str:
    """Driving command from the GT future (docs/conventions.md#ego-motion-and-the-command).

    Args:
        future_positions: [S, 2] metres, positions of frames t+1..t+S in the current ego frame;
            the last row is the 3 s waypoint.

    Returns:
        ``"left"`` if its lateral offset y >= 2 m, ``"right"`` if y <= -2 m, else
        ``"straight"``.
    """
    traj = np.asarray(future_positions, dtype=np.float64)
    if traj.ndim != 2 or traj.shape[1] != 2 or len(traj) < 1 or not np.isfinite(traj).all():
        raise ValueError(f"future_positions: expected finite [S, 2], got shape {traj.shape}")
    y = traj[-1, 1]
    if y >= COMMAND_LATERAL_THRESHOLD:
        return "left"
    if y <= -COMMAND_LATERAL_THRESHOLD:
        return "right"
    return "straight"
