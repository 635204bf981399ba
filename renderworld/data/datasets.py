"""Torch datasets over the converter's infos (batch_formats.md).

* :class:`Img2OccDataset` — one keyframe: six resized images with their intrinsics and poses,
  LiDAR-projected depth/semantic maps at the render size, Occ3D ground truth on a grid.
* :class:`OccSequenceDataset` — windows of ``history + future`` keyframes of one scene:
  occupancy, ego motion, the current command and future GT boxes, for tokenizer/world model.

Frames: ``cam_to_ego`` maps the camera (at its own timestamp) into the keyframe's ego frame (at
its LiDAR timestamp): ``inv(ego2global_lidar) @ ego2global_cam @ sensor2ego``. Planning
quantities are in the last history frame's ego frame (x forward, y left, metres).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from PIL import Image, UnidentifiedImageError
from torch.utils.data import Dataset

from renderworld.constants import (
    CAMERA_NAMES,
    COMMANDS,
    FUTURE_FRAMES,
    HISTORY_FRAMES,
    OCC3D_GRID,
    GridSpec,
    get_grid,
)
from renderworld.data.downsample import downsample_mask, downsample_occupancy, grid_factor
from renderworld.data.errors import DatasetError
from renderworld.data.infos import BOX_FIELDS, load_infos, stack_column
from renderworld.data.labels2d import load_labels2d
from renderworld.data.occ3d import load_occ3d_labels
from renderworld.geometry import invert_pose, scale_intrinsics

__all__ = ["Img2OccDataset", "OccSequenceDataset", "resolve_grid"]

NUM_CAMS = len(CAMERA_NAMES)


def resolve_grid(grid: str | GridSpec) -> GridSpec:
    """A grid by name (``renderworld.constants.GRIDS``) or a GridSpec of the Occ3D range.

    Raises:
        ValueError: for unknown names, other ranges, or shapes that do not divide Occ3D's.
    """
    spec = get_grid(grid) if isinstance(grid, str) else grid
    if not isinstance(spec, GridSpec):
        raise TypeError(f"grid: expected a grid name or GridSpec, got {type(grid).__name__}")
    if spec.range_min != OCC3D_GRID.range_min or spec.range_max != OCC3D_GRID.range_max:
        raise ValueError(
            f"grid: {spec.name} range {spec.range_min}..{spec.range_max} differs from Occ3D's "
            f"{OCC3D_GRID.range_min}..{OCC3D_GRID.range_max}"
        )
    grid_factor(OCC3D_GRID.shape, spec)
    return spec


def _as_infos(infos: str | os.PathLike | pd.DataFrame) -> pd.DataFrame:
    if isinstance(infos, pd.DataFrame):
        return infos.sort_values(["scene_index", "frame_index"], kind="stable").reset_index(
            drop=True
        )
    if isinstance(infos, (str, os.PathLike)):
        return load_infos(infos)
    raise TypeError(f"infos: expected a parquet path or a DataFrame, got {type(infos).__name__}")


def _size(name: str, value) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        h, w = (int(x) for x in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (H, W), got {value!r}") from None
    if h <= 0 or w <= 0:
        raise ValueError(f"{name}: expected positive (H, W), got {value!r}")
    return h, w


def _scene_positions(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Per row: first row of its scene and the scene's number of rows (rows sorted by scene)."""
    scene = df["scene_name"].to_numpy()
    starts = np.r_[0, np.flatnonzero(scene[1:] != scene[:-1]) + 1]
    if len(set(scene[starts])) != len(starts):
        raise DatasetError("infos: rows of a scene are not contiguous after sorting")
    lengths = np.diff(np.r_[starts, len(scene)])
    first = np.repeat(starts, lengths)
    count = np.repeat(lengths, lengths)
    return first, count


class _InfosBase(Dataset):
    """Shared loading of infos, poses and Occ3D labels."""

    def __init__(self, infos, data_root, grid):
        self.infos = _as_infos(infos)
        if len(self.infos) == 0:
            raise ValueError("infos: expected at least one keyframe, got an empty table")
        self.data_root = Path(data_root)
        if not self.data_root.is_dir():
            raise DatasetError(f"data_root: folder {self.data_root} does not exist")
        self.grid = resolve_grid(grid)
        self.ego2global = stack_column(self.infos, "ego2global", (4, 4))
        self.scene_first, self.scene_count = _scene_positions(self.infos)

    def _occ(self, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(semantics, mask_camera, mask_lidar) of a labels.npz on the configured grid."""
        labels = load_occ3d_labels(path)
        try:
            f = grid_factor(labels.shape, self.grid)
        except ValueError as exc:
            raise DatasetError(f"{path}: {exc}") from None
        return (
            downsample_occupancy(labels.semantics, f),
            downsample_mask(labels.mask_camera, f),
            downsample_mask(labels.mask_lidar, f),
        )


class Img2OccDataset(_InfosBase):
    """Keyframes for Img2Occ training (see module docstring and batch_formats.md).

    Args:
        infos: an ``infos_<split>.parquet`` path or a DataFrame from ``load_infos``.
        data_root: the dataset folder (images and ``gts/`` are relative to it).
        input_size: (H_in, W_in) network input size; images are resized bilinearly and
            intrinsics scaled by ``(W_in / W_img, H_in / H_img)``.
        render_size: (H_r, W_r) of the depth/semantic maps and ``render_intrinsics``; None uses
            the stored label resolution (which must then be the same for all cameras).
        grid: grid name or GridSpec of the Occ3D range for ``occ`` and masks.
        adjacent_frames: k; the k previous and k next keyframes' cameras (same scene, clamped at
            its ends) come as label-only views, offsets ordered -k..-1, +1..+k.
        labels_root: base folder of the infos' out-relative ``labels2d_path``; default the
            infos file's folder (``df.attrs['infos_dir']``), else ``data_root``.
        load_occ: load Occ3D ground truth when the row has one.

    Item (dict): images [C,3,H_in,W_in] float32 in [0,1]; intrinsics [C,3,3]; render_intrinsics
    [C,3,3]; cam_to_ego [C,4,4]; depth [C,H_r,W_r] float32 metres (0 = no point); semantics
    [C,H_r,W_r] int64 (255 = ignore); with GT: occ uint8 [X,Y,Z], mask_camera, mask_lidar bool
    [X,Y,Z]; with k > 0: adj_cam_to_ego [2kC,4,4], adj_render_intrinsics [2kC,3,3], adj_depth,
    adj_semantics [2kC,H_r,W_r]; meta {sample_token, scene}.
    """

    def __init__(
        self,
        infos,
        data_root,
        input_size=(256, 448),
        render_size=None,
        grid: str | GridSpec = "coarse",
        adjacent_frames: int = 0,
        labels_root=None,
        load_occ: bool = True,
    ):
        super().__init__(infos, data_root, grid)
        self.input_size = _size("input_size", input_size)
        self.render_size = _size("render_size", render_size)
        if not isinstance(adjacent_frames, int) or adjacent_frames < 0:
            raise ValueError(f"adjacent_frames: expected an integer >= 0, got {adjacent_frames!r}")
        self.adjacent_frames = adjacent_frames
        self.load_occ = load_occ
        if labels_root is None:
            labels_root = self.infos.attrs.get("infos_dir", self.data_root)
        self.labels_root = Path(labels_root)
        df = self.infos
        self.K = np.stack(
            [stack_column(df, f"cam{c}_intrinsics", (3, 3)) for c in range(NUM_CAMS)], 1
        )
        self.sensor2ego = np.stack(
            [stack_column(df, f"cam{c}_sensor2ego", (4, 4)) for c in range(NUM_CAMS)], 1
        )
        self.cam_ego2global = np.stack(
            [stack_column(df, f"cam{c}_ego2global", (4, 4)) for c in range(NUM_CAMS)], 1
        )
        self.image_hw = np.stack(
            [df[[f"cam{c}_height", f"cam{c}_width"]].to_numpy(np.int64) for c in range(NUM_CAMS)],
            1,
        )  # [N, C, 2]
        if (df["labels2d_path"] == "").any():
            row = df[df["labels2d_path"] == ""].iloc[0]
            raise DatasetError(
                f"infos: sample {row['sample_token']} has no 2-D labels (converted with "
                "labels=false?)"
            )

    def __len__(self) -> int:
        return len(self.infos)

    def _cam_to_ego(self, row: int, ref: int) -> np.ndarray:
        """[C, 4, 4] cameras of ``row`` into the ego frame of keyframe ``ref``."""
        return invert_pose(self.ego2global[ref]) @ self.cam_ego2global[row] @ self.sensor2ego[row]

    def _labels(self, row: int):
        path = Path(self.infos.at[row, "labels2d_path"])
        path = path if path.is_absolute() else self.labels_root / path
        cameras, labels = load_labels2d(path)
        if tuple(cameras) != CAMERA_NAMES:
            raise DatasetError(f"{path}: cameras {cameras}, expected {list(CAMERA_NAMES)}")
        sizes = {(lab.height, lab.width) for lab in labels}
        size = self.render_size
        if size is None:
            if len(sizes) != 1:
                raise DatasetError(f"{path}: label sizes {sorted(sizes)} differ; set render_size")
            size = sizes.pop()
        dense = [lab.densify(size) for lab in labels]
        depth = np.stack([d for d, _ in dense])
        sem = np.stack([s for _, s in dense]).astype(np.int64)
        return depth, sem, self._scaled_K(row, size)

    def _scaled_K(self, row: int, size: tuple[int, int]) -> np.ndarray:
        """[C, 3, 3] intrinsics of ``row``'s cameras for images resized to ``size`` (H, W)."""
        hw = self.image_hw[row]
        return np.stack(
            [
                scale_intrinsics(self.K[row, c], size[1] / hw[c, 1], size[0] / hw[c, 0])
                for c in range(NUM_CAMS)
            ]
        )

    def _images(self, row: int):
        h_in, w_in = self.input_size
        images = np.empty((NUM_CAMS, 3, h_in, w_in), dtype=np.float32)
        for c in range(NUM_CAMS):
            path = self.data_root / self.infos.at[row, f"cam{c}_path"]
            try:
                with Image.open(path) as im:
                    if im.size != (self.image_hw[row, c, 1], self.image_hw[row, c, 0]):
                        raise DatasetError(
                            f"{path}: image is {im.size[0]}x{im.size[1]}, infos say "
                            f"{self.image_hw[row, c, 1]}x{self.image_hw[row, c, 0]}"
                        )
                    im = im.convert("RGB").resize((w_in, h_in), Image.Resampling.BILINEAR)
                    images[c] = np.asarray(im, dtype=np.float32).transpose(2, 0, 1) / 255.0
            except FileNotFoundError:
                raise DatasetError(f"{path}: image file is missing") from None
            except (UnidentifiedImageError, OSError) as exc:
                raise DatasetError(f"{path}: not a readable image ({exc})") from exc
        return images, self._scaled_K(row, self.input_size)

    def _neighbours(self, row: int) -> list[int]:
        first, count = self.scene_first[row], self.scene_count[row]
        pos = row - first
        k = self.adjacent_frames
        offsets = [*range(-k, 0), *range(1, k + 1)]
        return [first + min(max(pos + d, 0), count - 1) for d in offsets]

    def __getitem__(self, index: int) -> dict:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} keyframes")
        row = int(index) % len(self)
        images, k_in = self._images(row)
        depth, sem, k_r = self._labels(row)
        item = {
            "images": torch.from_numpy(images),
            "intrinsics": torch.from_numpy(k_in.astype(np.float32)),
            "render_intrinsics": torch.from_numpy(k_r.astype(np.float32)),
            "cam_to_ego": torch.from_numpy(self._cam_to_ego(row, row).astype(np.float32)),
            "depth": torch.from_numpy(depth),
            "semantics": torch.from_numpy(sem),
        }
        occ_path = self.infos.at[row, "occ_path"]
        if self.load_occ and occ_path:
            occ, mask_cam, mask_lidar = self._occ(self.data_root / occ_path)
            item["occ"] = torch.from_numpy(occ)
            item["mask_camera"] = torch.from_numpy(mask_cam)
            item["mask_lidar"] = torch.from_numpy(mask_lidar)
        if self.adjacent_frames:
            adj = [(n, *self._labels(n)) for n in self._neighbours(row)]
            poses = np.concatenate([self._cam_to_ego(n, row) for n, *_ in adj])
            item["adj_cam_to_ego"] = torch.from_numpy(poses.astype(np.float32))
            item["adj_render_intrinsics"] = torch.from_numpy(
                np.concatenate([a[3] for a in adj]).astype(np.float32)
            )
            item["adj_depth"] = torch.from_numpy(np.concatenate([a[1] for a in adj]))
            item["adj_semantics"] = torch.from_numpy(np.concatenate([a[2] for a in adj]))
        item["meta"] = {
            "sample_token": str(self.infos.at[row, "sample_token"]),
            "scene": str(self.infos.at[row, "scene_name"]),
        }
        return item


def _boxes(cell, frames: range) -> list[np.ndarray]:
    """[len(frames)] arrays [M_k, 6] from a ``future_boxes`` cell."""
    n = len(BOX_FIELDS)
    return [np.asarray(list(cell[k]), dtype=np.float64).reshape(-1, n) for k in frames]


class OccSequenceDataset(_InfosBase):
    """Windows of consecutive keyframes of one scene, for the tokenizer and world model.

    Args:
        infos: an ``infos_<split>.parquet`` path or a DataFrame from ``load_infos``.
        data_root: the dataset folder (``occ_path`` is relative to it).
        history: frames up to and including the current one (default 5: t-4..t).
        future: frames after it (default 6: t+1..t+6, at most ``FUTURE_FRAMES`` for boxes).
        grid: grid name or GridSpec of the Occ3D range.
        occ_root: folder of exported pseudo labels laid out like ``gts/``
            (``<occ_root>/<scene>/<token>/labels.npz``; an ``occ_root`` holding a ``gts/`` folder
            is read inside it); default the dataset's own Occ3D gts (``occ_path``). Files of a
            finer grid are down-sampled to ``grid``.
        max_boxes: M, boxes per future frame (padded); default the most any window has. Frames
            with more keep the M nearest to the ego.
        cache_frames: keyframes whose grid-sampled occupancy is kept in memory (least recently
            used dropped); overlapping windows then load each file about once.

    Item (dict): occ uint8 [T,X,Y,Z] (each frame in its own ego frame); mask_camera bool
    [T,X,Y,Z]; ego_displacements float32 [T-1,2]; future_traj float32 [F,2]; future_mask bool
    [F]; command int64 (index into COMMANDS, of the last history frame); future_boxes float32
    [F,M,6] ``[x, y, length, width, yaw, occ3d_class]`` and future_boxes_mask bool [F,M], in
    the last history frame's ego frame; meta {scene, sample_tokens [T]}. Windows never cross
    scenes.
    """

    def __init__(
        self,
        infos,
        data_root,
        history: int = HISTORY_FRAMES,
        future: int = FUTURE_FRAMES,
        grid: str | GridSpec = "coarse",
        occ_root=None,
        max_boxes: int | None = None,
        cache_frames: int = 32,
    ):
        super().__init__(infos, data_root, grid)
        if not isinstance(cache_frames, int) or cache_frames < 0:
            raise ValueError(f"cache_frames: expected an integer >= 0, got {cache_frames!r}")
        self.cache_frames = cache_frames
        self._cache: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        if not isinstance(history, int) or history < 1:
            raise ValueError(f"history: expected an integer >= 1, got {history!r}")
        if not isinstance(future, int) or not 0 <= future <= FUTURE_FRAMES:
            raise ValueError(f"future: expected an integer in 0..{FUTURE_FRAMES}, got {future!r}")
        self.history, self.future = history, future
        span = history + future
        starts = [
            first + j
            for first, count in sorted(set(zip(self.scene_first, self.scene_count)))
            for j in range(count - span + 1)
        ]
        if not starts:
            raise ValueError(
                f"history/future: windows of {span} keyframes need a scene that long; the "
                f"longest has {int(self.scene_count.max())}"
            )
        self.starts = np.asarray(starts, dtype=np.int64)
        self.occ_root = None if occ_root is None else Path(occ_root)
        if self.occ_root is not None and (self.occ_root / "gts").is_dir():
            self.occ_root = self.occ_root / "gts"
        if self.occ_root is None:
            empty = self.infos["occ_path"] == ""
            if empty.any():
                row = self.infos[empty].iloc[0]
                raise DatasetError(
                    f"infos: sample {row['sample_token']} of {row['scene_name']} has no Occ3D gt "
                    "(occ_path is empty); pass occ_root with exported labels"
                )
        cells = self.infos["future_boxes"].to_numpy()
        self._future_boxes = [_boxes(cells[i], range(1, future + 1)) for i in range(len(cells))]
        most = max((len(b) for boxes in self._future_boxes for b in boxes), default=0)
        if max_boxes is not None and (not isinstance(max_boxes, int) or max_boxes < 0):
            raise ValueError(f"max_boxes: expected an integer >= 0, got {max_boxes!r}")
        self.max_boxes = most if max_boxes is None else max_boxes

    def __len__(self) -> int:
        return len(self.starts)

    def _occ_path(self, row: int) -> Path:
        if self.occ_root is None:
            return self.data_root / self.infos.at[row, "occ_path"]
        scene, token = self.infos.at[row, "scene_name"], self.infos.at[row, "sample_token"]
        return self.occ_root / scene / token / "labels.npz"

    def _frame_occ(self, row: int) -> tuple[np.ndarray, np.ndarray]:
        if row in self._cache:
            self._cache.move_to_end(row)
            return self._cache[row]
        occ, mask_cam, _ = self._occ(self._occ_path(row))
        if self.cache_frames:
            self._cache[row] = (occ, mask_cam)
            if len(self._cache) > self.cache_frames:
                self._cache.popitem(last=False)
        return occ, mask_cam

    def __getitem__(self, index: int) -> dict:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} windows")
        start = int(self.starts[int(index) % len(self)])
        rows = list(range(start, start + self.history + self.future))
        occ, mask_cam = zip(*(self._frame_occ(r) for r in rows))
        poses = self.ego2global[rows]
        disp = (invert_pose(poses[:-1]) @ poses[1:])[:, :2, 3]
        last = rows[self.history - 1]
        traj = (invert_pose(poses[self.history - 1]) @ poses[self.history :])[:, :2, 3]
        m = self.max_boxes
        boxes = np.zeros((self.future, m, len(BOX_FIELDS)), dtype=np.float32)
        boxes_mask = np.zeros((self.future, m), dtype=bool)
        for f, b in enumerate(self._future_boxes[last]):
            if len(b) > m:
                b = b[np.argsort(np.hypot(b[:, 0], b[:, 1]), kind="stable")[:m]]
            boxes[f, : len(b)] = b
            boxes_mask[f, : len(b)] = True
        return {
            "occ": torch.from_numpy(np.stack(occ)),
            "mask_camera": torch.from_numpy(np.stack(mask_cam)),
            "ego_displacements": torch.from_numpy(disp.astype(np.float32)),
            "future_traj": torch.from_numpy(traj.reshape(self.future, 2).astype(np.float32)),
            "future_mask": torch.ones(self.future, dtype=torch.bool),
            "command": torch.tensor(COMMANDS.index(self.infos.at[last, "command"])),
            "future_boxes": torch.from_numpy(boxes),
            "future_boxes_mask": torch.from_numpy(boxes_mask),
            "meta": {
                "scene": str(self.infos.at[last, "scene_name"]),
                "sample_tokens": [str(self.infos.at[r, "sample_token"]) for r in rows],
            },
        }
