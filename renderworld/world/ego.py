"""Ego-motion quantities from ego poses, in the world model's conventions.

These pin the displacement/trajectory convention in code (see :mod:`renderworld.world.config`)
so datasets, the planner API and the metrics compute it the same way:

* positions ``p[k]`` = origin of ego frame k (rear axle; docs/conventions.md#frames - VAD uses the
  LiDAR origin instead, which differs by centimetres while turning) expressed in the **current** ego
  frame (x forward, y left), metres;
* ``d[i] = p[i + 1] - p[i]`` (VAD's per-step offsets); the future trajectory is
  ``p[t + 1 .. t + S]`` = cumulative sum of the future ``d``;
* the command follows docs/conventions.md#ego-motion-and-the-command from the lateral offset of
  the last future waypoint (3 s) (:func:`command_from_trajectory`, the rule the data converters
  apply too).

:func:`frame_poses_from_poses` lives with the other pose algebra in
:mod:`renderworld.geometry.poses` (the datasets use it too) and is re-exported here.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import COMMAND_LATERAL_THRESHOLD, COMMANDS
from renderworld.geometry.poses import frame_poses_from_poses

__all__ = [
    "command_from_trajectory",
    "command_indices",
    "displacements_from_poses",
    "frame_poses_from_poses",
]


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


def command_from_trajectory(future_positions, mask=None) -> str:
    """Driving command from a future trajectory: the package's one command rule.

    The lateral offset ``y`` of the 3 s waypoint (the last of the S rows) in the current ego
    frame: ``y >= 2 m`` (``COMMAND_LATERAL_THRESHOLD``) -> ``"left"``, ``y <= -2 m`` ->
    ``"right"``, else ``"straight"``. With ``mask``, the last valid row decides (the 3 s point
    lies past the scene end); with no valid row at all (a scene's last keyframe) the command is
    ``"straight"``. The infos derive it from the GT future (as VAD / UniAD do), so a model that
    reads it reads a summary of the future.

    Args:
        future_positions: [S, 2] metres, positions of frames t+1..t+S in the current ego frame.
        mask: optional [S] bool validity of the rows (None = all valid).

    Returns:
        One of ``renderworld.constants.COMMANDS``.

    Raises:
        ValueError: not a finite [S, 2] array (valid rows), a mask of another length.
    """
    traj = np.asarray(future_positions, dtype=np.float64)
    if traj.ndim != 2 or traj.shape[1] != 2 or (mask is None and len(traj) < 1):
        raise ValueError(f"future_positions: expected finite [S, 2], got shape {traj.shape}")
    valid = np.ones(len(traj), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if valid.shape != traj.shape[:1]:
        raise ValueError(f"mask: expected [{len(traj)}] bool, got shape {valid.shape}")
    if not np.isfinite(traj[valid]).all():
        raise ValueError(f"future_positions: expected finite [S, 2], got shape {traj.shape}")
    rows = np.flatnonzero(valid)
    if rows.size == 0:
        return "straight"
    y = traj[rows[-1], 1]
    if y >= COMMAND_LATERAL_THRESHOLD:
        return "left"
    if y <= -COMMAND_LATERAL_THRESHOLD:
        return "right"
    return "straight"


def command_indices(trajectories) -> np.ndarray:
    """The command of each of B trajectories, as indices into ``COMMANDS``.

    Args:
        trajectories: [B, S, 2] metres, frames t+1..t+S in each window's current ego frame
            (e.g. a constant-turn-rate extrapolation of the history: a command that reads no
            future).

    Returns:
        [B] int64, ``COMMANDS.index(command_from_trajectory(trajectories[b]))``.
    """
    traj = np.asarray(trajectories, dtype=np.float64)
    if traj.ndim != 3 or traj.shape[-1] != 2:
        raise ValueError(f"trajectories: expected [B, S, 2], got shape {traj.shape}")
    return np.array([COMMANDS.index(command_from_trajectory(t)) for t in traj], dtype=np.int64)
