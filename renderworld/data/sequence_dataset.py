"""OccSequenceDataset: windows of keyframes of one scene (docs/formats.md#dataset-items)."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from renderworld.constants import COMMANDS, FUTURE_FRAMES, HISTORY_FRAMES, GridSpec
from renderworld.data.dataset_base import InfosDataset
from renderworld.data.errors import DatasetError
from renderworld.data.frame_cache import FrameCache
from renderworld.data.infos import BOX_FIELDS
from renderworld.geometry.poses import frame_poses_from_poses

__all__ = ["OccSequenceDataset"]


def _boxes(cell, frames: range) -> list[np.ndarray]:
    """[len(frames)] arrays [M_k, len(BOX_FIELDS)] from a ``future_boxes`` cell."""
    n = len(BOX_FIELDS)
    return [np.asarray(list(cell[k]), dtype=np.float64).reshape(-1, n) for k in frames]


class OccSequenceDataset(InfosDataset):
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
        frame_cache: None, or a folder where each file's grid-sampled occupancy and camera mask
            are kept across runs (:class:`renderworld.data.frame_cache.FrameCache`; keyed by
            the file's path, size, mtime and hash, the grid and the code version).

    Item (dict):
        occ: uint8 [T,X,Y,Z], each frame in its own ego frame.
        mask_camera: bool [T,X,Y,Z].
        ego_displacements: float32 [T-1,2], ``p[i+1] - p[i]`` with ``p`` the frames' positions
            in the last history frame's ego frame (metres; VAD convention, as PlanRequest).
        history_poses: float32 [H,3], (x, y, yaw) of the history frames in the last history
            frame's ego frame (metres, radians; the last row is zeros).
        future_poses: float32 [F,3], (x, y, yaw) of the future frames in that frame: where
            each future occupancy frame lies (both from
            :func:`renderworld.geometry.poses.frame_poses_from_poses`).
        future_traj: float32 [F,2], positions of the future frames in that frame (metres).
        future_mask: bool [F].
        command: int64, index into COMMANDS, of the last history frame.
        future_boxes: float32 [F,M,7] ``[x, y, length, width, yaw, occ3d_class, instance]`` in
            the last history frame's ego frame (``instance``: the road user's index, the same
            in every frame); future_boxes_mask bool [F,M].
        current_boxes: float32 [M,7] the boxes of the last history frame (the same columns);
            current_boxes_mask bool [M].
        meta: {scene, sample_tokens [T]}. Windows never cross scenes.
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
        frame_cache=None,
    ):
        super().__init__(infos, data_root, grid)
        self.frame_cache = None if frame_cache is None else FrameCache(frame_cache)
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
        self._future_boxes = [_boxes(cells[i], range(0, future + 1)) for i in range(len(cells))]
        most = max((len(b) for boxes in self._future_boxes for b in boxes), default=0)
        if max_boxes is not None and (not isinstance(max_boxes, int) or max_boxes < 0):
            raise ValueError(f"max_boxes: expected an integer >= 0, got {max_boxes!r}")
        self.max_boxes = most if max_boxes is None else max_boxes

    def __len__(self) -> int:
        return len(self.starts)

    def _occ_path(self, row: int) -> Path:
        if self.occ_root is None:
            return self.data_root / self.text["occ_path"][row]
        scene, token = self.text["scene_name"][row], self.text["sample_token"][row]
        return self.occ_root / scene / token / "labels.npz"

    def _frame_occ(self, row: int) -> tuple[np.ndarray, np.ndarray]:
        if row in self._cache:
            self._cache.move_to_end(row)
            return self._cache[row]
        path = self._occ_path(row)
        if self.frame_cache is not None and path.is_file():
            occ, mask_cam = self.frame_cache.get(path, self.grid, lambda p: self._occ(p)[:2])
        else:
            occ, mask_cam, _ = self._occ(path)
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
        last = rows[self.history - 1]
        # (x, y, yaw) of every frame in the current (last history) ego frame; displacements are
        # the per-step differences of the positions (VAD convention, as
        # renderworld.planning.PlanRequest), so the future trajectory is exactly the cumulative
        # sum of the future displacements.
        frame = frame_poses_from_poses(poses, self.history - 1)
        pos = frame[:, :2]
        disp = np.diff(pos, axis=0)
        m = self.max_boxes
        boxes = np.zeros((self.future + 1, m, len(BOX_FIELDS)), dtype=np.float32)
        boxes_mask = np.zeros((self.future + 1, m), dtype=bool)
        for f, b in enumerate(self._future_boxes[last]):
            if len(b) > m:
                b = b[np.argsort(np.hypot(b[:, 0], b[:, 1]), kind="stable")[:m]]
            boxes[f, : len(b)] = b
            boxes_mask[f, : len(b)] = True
        return {
            "occ": torch.from_numpy(np.stack(occ)),
            "mask_camera": torch.from_numpy(np.stack(mask_cam)),
            "ego_displacements": torch.from_numpy(disp.astype(np.float32)),
            "history_poses": torch.from_numpy(frame[: self.history].astype(np.float32)),
            "future_poses": torch.from_numpy(frame[self.history :].astype(np.float32)),
            "future_traj": torch.from_numpy(pos[self.history :].astype(np.float32)),
            "future_mask": torch.ones(self.future, dtype=torch.bool),
            "command": torch.tensor(COMMANDS.index(self.text["command"][last])),
            "future_boxes": torch.from_numpy(boxes[1:]),
            "future_boxes_mask": torch.from_numpy(boxes_mask[1:]),
            "current_boxes": torch.from_numpy(boxes[0]),
            "current_boxes_mask": torch.from_numpy(boxes_mask[0]),
            "meta": {
                "scene": (self.text["scene_name"][last]),
                "scene_description": self.text.get("scene_description", [""] * (last + 1))[last],
                "sample_tokens": [(self.text["sample_token"][r]) for r in rows],
            },
        }
