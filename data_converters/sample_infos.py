"""Per-keyframe info rows (docs/formats.md#infos) from a :class:`NuScenesReader`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError

from data_converters.fast_index import TableIndex
from data_converters.projection import CameraView
from data_converters.trajectory import (
    boxes_in_ego_frame,
    ego_future,
    ego_history,
)
from renderworld.constants import CAMERA_NAMES, FUTURE_FRAMES, LIDAR_NAME
from renderworld.data import DatasetError
from renderworld.world.ego import command_from_trajectory

__all__ = ["SceneFrames", "scene_frames", "camera_views", "info_rows", "image_size", "occ_path"]


@dataclass(frozen=True)
class SceneFrames:
    """A scene's keyframes in time order.

    Attributes:
        name: scene name.
        index: scene index in the dataset's scene table.
        tokens: [N] sample tokens.
        lidar_tokens: [N] LIDAR_TOP keyframe sample_data tokens.
        ego_to_global: [N, 4, 4] ego poses at the LiDAR keyframe timestamps.
    """

    name: str
    index: int
    tokens: list[str]
    lidar_tokens: list[str]
    ego_to_global: np.ndarray

    def __len__(self) -> int:
        return len(self.tokens)


def scene_frames(tables: TableIndex, name: str, index: int) -> SceneFrames:
    """Collect a scene's keyframes and their LiDAR-time ego poses."""
    tokens = tables.reader.scene_samples(name)
    lidar = [tables.reader.sample_data_token(t, LIDAR_NAME) for t in tokens]
    poses = np.stack([tables.ego_to_global(sd) for sd in lidar])
    return SceneFrames(name, index, tokens, lidar, poses)


def image_size(tables: TableIndex, sd_token: str) -> tuple[int, int]:
    """(H, W) of a camera image, checked against its sample_data record.

    Reads only the image header. Raises DatasetError naming the file when it is missing, not
    an image, or its size differs from the record's width/height. An occupancy-only dataset
    (:mod:`renderworld.data.occupancy_only`) has no images by design: its records' size is
    returned.
    """
    path = tables.reader.path(tables.field(sd_token, "filename"))
    rw, rh = int(tables.field(sd_token, "width")), int(tables.field(sd_token, "height"))
    if not path.is_file() and tables.reader.occupancy_only and rw > 0 and rh > 0:
        return rh, rw  # no images by design: the record's size (infos only, no 2-D labels)
    if not path.is_file():
        raise DatasetError(f"{path}: image file is missing")
    try:
        with Image.open(path) as im:
            w, h = im.size
    except (UnidentifiedImageError, OSError) as exc:
        raise DatasetError(f"{path}: not a readable image ({exc})") from exc
    if (rw, rh) != (0, 0) and (rw, rh) != (w, h):
        raise DatasetError(f"{path}: image is {w}x{h} but sample_data {sd_token!r} says {rw}x{rh}")
    return h, w


def camera_views(
    tables: TableIndex, sample_token: str, label_size_fn
) -> tuple[list[str], list[CameraView]]:
    """The six cameras of a keyframe (CAMERA_NAMES order), each at its own timestamp.

    Args:
        tables: the dataset's table index.
        sample_token: keyframe.
        label_size_fn: (H, W) image size -> (H_label, W_label).

    Returns:
        ``([6] camera sample_data tokens, [6] CameraView)``.
    """
    tokens, views = [], []
    for cam in CAMERA_NAMES:
        sd = tables.reader.sample_data_token(sample_token, cam)
        size = image_size(tables, sd)
        tokens.append(sd)
        views.append(
            CameraView(
                K=tables.intrinsics(sd),
                sensor_to_ego=tables.sensor_to_ego(sd),
                ego_to_global=tables.ego_to_global(sd),
                image_size=size,
                label_size=label_size_fn(size),
            )
        )
    return tokens, views


def _flat(mat: np.ndarray) -> list[float]:
    return np.asarray(mat, dtype=np.float64).reshape(-1).tolist()


def occ_path(tables: TableIndex, scene: str, sample_token: str) -> str:
    """Dataroot-relative ``gts/<scene>/<token>/labels.npz`` if that file exists, else ''."""
    rel = f"gts/{scene}/{sample_token}/labels.npz"
    return rel if tables.reader.path(rel).is_file() else ""


def info_rows(
    tables: TableIndex,
    frames: SceneFrames,
    split: str,
    cams: list[tuple[list[str], list[CameraView]]],
    labels2d_paths: list[str],
) -> list[dict]:
    """Info rows of one scene (docs/formats.md#infos), in frame order.

    Args:
        tables: the dataset's table index.
        frames: the scene's keyframes.
        split: split name of the scene.
        cams: per frame, the output of :func:`camera_views`.
        labels2d_paths: per frame, the out-relative path of its 2-D labels file ('' if none).

    Returns:
        [N] dicts with the infos columns.
    """
    reader = tables.reader
    boxes = [tables.sample_boxes(t) for t in frames.tokens]
    rows = []
    for i, token in enumerate(frames.tokens):
        lidar = frames.lidar_tokens[i]
        e_t = frames.ego_to_global[i]
        hist, hist_mask = ego_history(frames.ego_to_global, i)
        fut, fut_mask = ego_future(frames.ego_to_global, i)
        future_boxes = []
        for k in range(i, i + FUTURE_FRAMES + 1):
            future_boxes.append(
                boxes_in_ego_frame(boxes[k], e_t).tolist() if k < len(frames) else []
            )
        row = {
            "scene_name": frames.name,
            "scene_description": str(
                reader.table("scene").at[reader.scene_token(frames.name), "description"]
            ),
            "scene_index": frames.index,
            "frame_index": i,
            "sample_token": token,
            "timestamp": int(reader.table("sample").at[token, "timestamp"]),
            "split": split,
        }
        sd_tokens, views = cams[i]
        for c, (sd, view) in enumerate(zip(sd_tokens, views)):
            row[f"cam{c}_path"] = tables.field(sd, "filename")
            row[f"cam{c}_intrinsics"] = _flat(view.K)
            row[f"cam{c}_width"] = view.image_size[1]
            row[f"cam{c}_height"] = view.image_size[0]
            row[f"cam{c}_sensor2ego"] = _flat(view.sensor_to_ego)
            row[f"cam{c}_ego2global"] = _flat(view.ego_to_global)
            row[f"cam{c}_timestamp"] = int(tables.field(sd, "timestamp"))
        row.update(
            {
                "lidar_token": lidar,
                "lidar_path": tables.field(lidar, "filename"),
                "lidar2ego": _flat(tables.sensor_to_ego(lidar)),
                "ego2global": _flat(e_t),
                "occ_path": occ_path(tables, frames.name, token),
                "labels2d_path": labels2d_paths[i],
                "ego_history": hist.reshape(-1).tolist(),
                "ego_history_mask": hist_mask.tolist(),
                "ego_future": fut.reshape(-1).tolist(),
                "ego_future_mask": fut_mask.tolist(),
                "command": command_from_trajectory(fut, fut_mask),
                "future_boxes": future_boxes,
            }
        )
        rows.append(row)
    return rows
