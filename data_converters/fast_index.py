"""Vectorised look-ups over a reader's tables, for converting tens of thousands of keyframes.

``NuScenesReader`` accessors go through ``DataFrame.loc`` per call (~0.5 ms); a trainval
conversion asks for ~1M calibrations, poses and file names. :class:`TableIndex` reads the
columns once into plain dicts and caches each distinct pose matrix, and groups all annotation
boxes by sample in one pass. Values are identical to the reader's (tested).
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import pandas as pd

from renderworld.constants import LIDARSEG_CLASSES, LIDARSEG_TO_OCC3D, OTHERS_ID
from renderworld.data import DatasetError, NuScenesReader
from renderworld.geometry import pose_matrix

__all__ = ["TableIndex"]

_BOX_COLUMNS = ("center_x", "center_y", "center_z", "width", "length", "height", "yaw",
                "occ3d_class", "instance_index")  # fmt: skip


class TableIndex:
    """Fast per-token access to sample_data fields, calibrations, ego poses and boxes.

    Args:
        reader: an open dataset.
    """

    def __init__(self, reader: NuScenesReader):
        self.reader = reader
        sd = reader.table("sample_data")
        self._sd = {
            col: dict(zip(sd.index, sd[col].tolist()))
            for col in ("filename", "timestamp", "calibrated_sensor_token", "ego_pose_token",
                        "width", "height", "is_key_frame", "prev", "next")
        }  # fmt: skip
        self._cs = reader.table("calibrated_sensor")
        self._ep = reader.table("ego_pose")
        self._cs_pose: dict[str, np.ndarray] = {}
        self._cs_k: dict[str, np.ndarray] = {}
        self._ep_pose: dict[str, np.ndarray] = {}
        self._boxes: dict[str, pd.DataFrame] | None = None

    def field(self, sd_token: str, name: str):
        """A sample_data field (filename, timestamp, width, height, is_key_frame, prev, next)."""
        try:
            return self._sd[name][sd_token]
        except KeyError:
            raise DatasetError(f"sample_data.json: no record with token {sd_token!r}") from None

    def sensor_to_ego(self, sd_token: str) -> np.ndarray:
        """[4, 4] calibrated_sensor of a sample_data record (cached per calibration)."""
        cs = self.field(sd_token, "calibrated_sensor_token")
        if cs not in self._cs_pose:
            rec = self._cs.loc[cs]
            self._cs_pose[cs] = pose_matrix(rec["translation"], rec["rotation"])
        return self._cs_pose[cs]

    def intrinsics(self, sd_token: str) -> np.ndarray:
        """[3, 3] camera intrinsics (cached per calibration)."""
        cs = self.field(sd_token, "calibrated_sensor_token")
        if cs not in self._cs_k:
            self._cs_k[cs] = self.reader.intrinsics(sd_token)
        return self._cs_k[cs]

    def ego_to_global(self, sd_token: str) -> np.ndarray:
        """[4, 4] ego pose at a sample_data record's timestamp (cached per pose)."""
        ep = self.field(sd_token, "ego_pose_token")
        if ep not in self._ep_pose:
            rec = self._ep.loc[ep]
            self._ep_pose[ep] = pose_matrix(rec["translation"], rec["rotation"])
        return self._ep_pose[ep]

    @cached_property
    def lidarseg_files(self) -> dict[str, str]:
        """{LiDAR sample_data token: lidarseg filename}; empty without lidarseg."""
        if not self.reader.has_lidarseg:
            return {}
        ls = self.reader.table("lidarseg")
        return dict(zip(ls["sample_data_token"], ls["filename"]))

    def sample_boxes(self, sample_token: str) -> pd.DataFrame:
        """Boxes of a sample in the global frame, columns as ``NuScenesReader.sample_boxes``
        (``center_*``, ``width``, ``length``, ``height``, ``yaw``, ``occ3d_class``,
        ``instance_index``)."""
        if self._boxes is None:
            self._boxes = self._group_boxes()
        empty = pd.DataFrame({c: np.zeros(0) for c in _BOX_COLUMNS})
        return self._boxes.get(sample_token, empty)

    def _group_boxes(self) -> dict[str, pd.DataFrame]:
        ann = self.reader.table("sample_annotation")
        if len(ann) == 0:
            return {}
        inst = self.reader.table("instance")
        cat = self.reader.table("category")
        name_to_occ = {n: LIDARSEG_TO_OCC3D[i] for i, n in enumerate(LIDARSEG_CLASSES)}
        cat_occ = cat["name"].map(lambda n: name_to_occ.get(n, OTHERS_ID))
        occ = ann["instance_token"].map(inst["category_token"]).map(cat_occ)
        centre = np.asarray(ann["translation"].tolist(), dtype=np.float64).reshape(-1, 3)
        size = np.asarray(ann["size"].tolist(), dtype=np.float64).reshape(-1, 3)
        q = np.asarray(ann["rotation"].tolist(), dtype=np.float64).reshape(-1, 4)
        w, x, y, z = q.T
        frame = pd.DataFrame(
            {
                "center_x": centre[:, 0], "center_y": centre[:, 1], "center_z": centre[:, 2],
                "width": size[:, 0], "length": size[:, 1], "height": size[:, 2],
                "yaw": np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
                "occ3d_class": occ.to_numpy(dtype=np.int64),
                "instance_index": inst.index.get_indexer(ann["instance_token"]).astype(np.int64),
            }
        )  # fmt: skip
        groups = ann.groupby("sample_token", sort=False).indices
        return {s: frame.iloc[idx].reset_index(drop=True) for s, idx in groups.items()}
