"""The keyframes of one scene as the viewer lays them out: tokens, times and ego poses.

The recording's ``world`` frame is the nuScenes global frame shifted so that the first shown
keyframe's ego origin is at (0, 0, 0) (global coordinates are kilometres; the viewer's camera
and float32 positions behave better near the origin). Axes are unchanged: x, y metres, z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import LIDAR_NAME
from renderworld.geometry import invert_pose

__all__ = ["SceneFrames", "scene_frames"]


@dataclass(frozen=True)
class SceneFrames:
    """Keyframes of one scene in time order.

    Attributes:
        scene: scene name.
        sample_tokens: [T] sample tokens.
        lidar_tokens: [T] LIDAR_TOP keyframe sample_data tokens.
        timestamps_us: [T] int64 LIDAR_TOP timestamps, microseconds.
        ego_to_world: [T, 4, 4] float64 ego→world poses at the LiDAR timestamps (``world`` =
            global shifted by ``origin``).
        origin: [3] float64 global position of ``world``'s origin, metres.
        first_index: index of ``sample_tokens[0]`` among all keyframes of the scene.
    """

    scene: str
    sample_tokens: list[str]
    lidar_tokens: list[str]
    timestamps_us: np.ndarray
    ego_to_world: np.ndarray
    origin: np.ndarray
    first_index: int = 0

    def __len__(self) -> int:
        return len(self.sample_tokens)

    def seconds(self, i: int) -> float:
        """Seconds from the first shown keyframe to keyframe ``i``."""
        return float(self.timestamps_us[i] - self.timestamps_us[0]) * 1e-6

    def positions_in(self, i: int, frames) -> np.ndarray:
        """[F, 2] x, y (metres) of keyframes ``frames`` in keyframe ``i``'s ego frame."""
        rel = invert_pose(self.ego_to_world[i]) @ self.ego_to_world[list(frames)]
        return rel[:, :2, 3].reshape(-1, 2)


def scene_frames(reader, scene: str, start: int = 0, max_frames: int | None = None) -> SceneFrames:
    """Collect a scene's keyframes from a :class:`~renderworld.data.NuScenesReader`.

    Args:
        reader: the dataset's reader.
        scene: scene name (e.g. ``"scene-0103"``) or token.
        start: first keyframe shown (0-based).
        max_frames: keyframes shown from ``start`` (None: to the end of the scene).

    Raises:
        ValueError: an unknown scene, or ``start`` / ``max_frames`` outside the scene.
    """
    names = reader.scene_names()
    if scene not in names and scene not in set(reader.table("scene").index):
        raise ValueError(f"scene: {scene!r} is not in {reader.dataroot}; scenes: {names}")
    tokens = reader.scene_samples(scene)
    if isinstance(start, bool) or not isinstance(start, int) or not 0 <= start < len(tokens):
        raise ValueError(f"start: expected an integer in 0..{len(tokens) - 1}, got {start!r}")
    if max_frames is not None and (
        isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1
    ):
        raise ValueError(f"max_frames: expected an integer >= 1 or None, got {max_frames!r}")
    stop = len(tokens) if max_frames is None else min(len(tokens), start + max_frames)
    tokens = tokens[start:stop]
    lidar = [reader.sample_data_token(t, LIDAR_NAME) for t in tokens]
    poses = np.stack([reader.ego_to_global(sd) for sd in lidar])
    origin = poses[0, :3, 3].copy()
    poses[:, :3, 3] -= origin
    return SceneFrames(
        scene=reader.scene_of_sample(tokens[0]),
        sample_tokens=list(tokens),
        lidar_tokens=lidar,
        timestamps_us=np.asarray([reader.timestamp(sd) for sd in lidar], dtype=np.int64),
        ego_to_world=poses,
        origin=origin,
        first_index=start,
    )
