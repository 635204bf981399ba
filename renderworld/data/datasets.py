"""Torch datasets over the converter's infos (docs/formats.md#dataset-items).

* :class:`Img2OccDataset` — one keyframe: six resized images with their intrinsics and poses,
  LiDAR-projected depth/semantic maps at the render size, Occ3D ground truth on a grid.
* :class:`OccSequenceDataset` — windows of ``history + future`` keyframes of one scene:
  occupancy, ego motion, the current command and future GT boxes, for tokenizer/world model.

Frames: ``cam_to_ego`` maps the camera (at its own timestamp) into the keyframe's ego frame (at
its LiDAR timestamp): ``inv(ego2global_lidar) @ ego2global_cam @ sensor2ego``. Planning
quantities are in the last history frame's ego frame (x forward, y left, metres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from renderworld.constants import CAMERA_NAMES, GridSpec
from renderworld.data.dataset_base import InfosDataset, check_size, resolve_grid
from renderworld.data.errors import DatasetError
from renderworld.data.infos import stack_column
from renderworld.data.labels2d import load_labels2d
from renderworld.data.sequence_dataset import OccSequenceDataset
from renderworld.geometry import invert_pose, scale_intrinsics

__all__ = ["Img2OccDataset", "OccSequenceDataset", "resolve_grid"]

NUM_CAMS = len(CAMERA_NAMES)


def _draft_scale(w: int, h: int, w_in: int, h_in: int) -> int:
    """Largest JPEG draft divisor s in (8, 4, 2) dividing W and H with W/s >= W_in, H/s >= H_in."""
    for s in (8, 4, 2):
        if w % s == 0 and h % s == 0 and w // s >= w_in and h // s >= h_in:
            return s
    return 1


class Img2OccDataset(InfosDataset):
    """Keyframes for Img2Occ training (see module docstring and docs/formats.md#dataset-items).

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
        self.input_size = check_size("input_size", input_size)
        self.render_size = check_size("render_size", render_size)
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
        path = Path(self.text["labels2d_path"][row])
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
        """([C, 3, H_in, W_in] float32 tensor in [0, 1], [C, 3, 3] intrinsics at the input size)."""
        h_in, w_in = self.input_size
        buf = np.empty((NUM_CAMS, h_in, w_in, 3), dtype=np.uint8)
        for c in range(NUM_CAMS):
            path = self.data_root / self.text[f"cam{c}_path"][row]
            h, w = (int(x) for x in self.image_hw[row, c])
            try:
                with Image.open(path) as im:
                    if im.size != (w, h):
                        raise DatasetError(
                            f"{path}: image is {im.size[0]}x{im.size[1]}, infos say {w}x{h}"
                        )
                    # JPEG DCT scaling by an exact divisor keeps the pixel-area mapping (pixel i
                    # covers [s i, s (i + 1)) of the original), so the intrinsics scale stays
                    # W_in / W; it only makes decoding cheaper before the bilinear resize.
                    s = _draft_scale(w, h, w_in, h_in)
                    if s > 1 and im.format == "JPEG":
                        im.draft("RGB", (w // s, h // s))
                    im = im.convert("RGB").resize((w_in, h_in), Image.Resampling.BILINEAR)
                    buf[c] = np.asarray(im)
            except FileNotFoundError:
                raise DatasetError(f"{path}: image file is missing") from None
            except (UnidentifiedImageError, OSError) as exc:
                raise DatasetError(f"{path}: not a readable image ({exc})") from exc
        images = torch.from_numpy(buf).permute(0, 3, 1, 2).float().div_(255.0).contiguous()
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
            "images": images,
            "intrinsics": torch.from_numpy(k_in.astype(np.float32)),
            "render_intrinsics": torch.from_numpy(k_r.astype(np.float32)),
            "cam_to_ego": torch.from_numpy(self._cam_to_ego(row, row).astype(np.float32)),
            "depth": torch.from_numpy(depth),
            "semantics": torch.from_numpy(sem),
        }
        occ_path = self.text["occ_path"][row]
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
            "sample_token": (self.text["sample_token"][row]),
            "scene": (self.text["scene_name"][row]),
        }
        return item
