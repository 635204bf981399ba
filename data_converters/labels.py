"""One keyframe's 2-D labels: gather its point sources (keyframe, sweeps, neighbours), project.

Sources: the LIDAR_TOP keyframe with its lidarseg labels (mapped to Occ3D; 255 when the dataset
has no lidarseg); optionally ``sweeps`` LiDAR sample_data records on each side along the
sample_data prev/next chain (depth only, label 255, unless the record is itself a labelled
keyframe); optionally the ``multiframe`` neighbouring keyframes of the same scene on each side,
keeping only their static-class points. Every source keeps its own ego pose, so the devkit chain
motion-compensates it into each camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from data_converters.fast_index import TableIndex
from data_converters.projection import (
    STATIC_CLASS_IDS,
    CameraView,
    PointSource,
    label_maps,
    unlabelled,
)
from data_converters.sample_infos import SceneFrames
from renderworld.constants import CAMERA_NAMES
from renderworld.data.labels2d import SparseLabels2D
from renderworld.geometry import DEVKIT_MIN_DEPTH

__all__ = ["sweep_tokens", "point_sources", "label_inputs", "make_labels"]

_POSE_TABLES = ("calibrated_sensor.json", "ego_pose.json", "sample_data.json", "lidarseg.json")


def sweep_tokens(tables: TableIndex, lidar_token: str, k: int) -> list[str]:
    """Up to ``k`` LiDAR sample_data tokens before and ``k`` after ``lidar_token`` (chain order).

    Returns:
        [<= 2k] tokens, previous ones nearest first, then next ones nearest first.
    """
    out = []
    for direction in ("prev", "next"):
        cur = lidar_token
        for _ in range(k):
            cur = tables.field(cur, direction)
            if not cur:
                break
            out.append(cur)
    return out


def _labelled_points(tables: TableIndex, sd_token: str) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] and Occ3D labels [N]: lidarseg for keyframes, 255 for sweeps.

    A keyframe of a dataset with lidarseg must have its labels (the reader raises otherwise).
    """
    reader = tables.reader
    pts = reader.lidar_points(sd_token)[:, :3]
    keyframe = bool(tables.field(sd_token, "is_key_frame"))
    if reader.has_lidarseg and keyframe:
        return pts, reader.lidarseg_labels(sd_token, occ3d=True)
    return pts, unlabelled(len(pts))


def _neighbours(frames: SceneFrames, index: int, m: int) -> list[int]:
    return [j for d in range(1, m + 1) for j in (index - d, index + d) if 0 <= j < len(frames)]


def point_sources(
    tables: TableIndex, frames: SceneFrames, index: int, sweeps: int = 0, multiframe: int = 0
) -> list[PointSource]:
    """The point sources labelling keyframe ``index`` of a scene (keyframe first)."""
    key = frames.lidar_tokens[index]
    out = []
    pts, labels = _labelled_points(tables, key)
    out.append(PointSource(pts, labels, tables.sensor_to_ego(key), frames.ego_to_global[index]))
    for sd in sweep_tokens(tables, key, sweeps):
        pts, labels = _labelled_points(tables, sd)
        out.append(PointSource(pts, labels, tables.sensor_to_ego(sd), tables.ego_to_global(sd)))
    for j in _neighbours(frames, index, multiframe):
        sd = frames.lidar_tokens[j]
        pts, labels = _labelled_points(tables, sd)
        static = np.isin(labels, STATIC_CLASS_IDS)
        out.append(
            PointSource(
                pts[static], labels[static], tables.sensor_to_ego(sd), frames.ego_to_global[j]
            )
        )
    return out


def label_inputs(
    tables: TableIndex, frames: SceneFrames, index: int, sweeps: int = 0, multiframe: int = 0
) -> list[Path]:
    """Files a keyframe's labels are made from (for the re-run "newer than inputs" check)."""
    reader = tables.reader
    tokens = [frames.lidar_tokens[index], *sweep_tokens(tables, frames.lidar_tokens[index], sweeps)]
    tokens += [frames.lidar_tokens[j] for j in _neighbours(frames, index, multiframe)]
    files = [reader.path(tables.field(t, "filename")) for t in tokens]
    seg = tables.lidarseg_files
    files += [reader.path(seg[t]) for t in tokens if t in seg]
    files += [reader.version_dir / name for name in _POSE_TABLES]
    return files


def make_labels(
    tables: TableIndex,
    frames: SceneFrames,
    index: int,
    views: list[CameraView],
    sweeps: int = 0,
    multiframe: int = 0,
    min_depth: float = DEVKIT_MIN_DEPTH,
) -> tuple[list[str], list[SparseLabels2D]]:
    """Sparse label maps of one keyframe's six cameras.

    Returns:
        ``(camera names [6], labels [6])`` in CAMERA_NAMES order.
    """
    sources = point_sources(tables, frames, index, sweeps, multiframe)
    return list(CAMERA_NAMES), label_maps(sources, views, min_depth)
