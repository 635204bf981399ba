"""A pandas reader for nuScenes-format datasets (real nuScenes or the package's simulator).

No devkit, no pyquaternion. Tables load lazily, once, on first use, and their references are
checked when they load (docs/conventions.md#errors-and-data-safety: a malformed dataset fails naming
file and record).

Frames: ``sensor_to_ego`` is the calibrated_sensor (sensor→ego), ``ego_to_global`` the
ego_pose (ego→global) of a sample_data record; both 4x4 float64. Quaternions [w, x, y, z].
"""

from __future__ import annotations

import os
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd

from renderworld.constants import (
    LIDAR_NAME,
    LIDARSEG_CLASSES,
    LIDARSEG_TO_OCC3D,
    NUSCENES_TABLES,
    OTHERS_ID,
    lidarseg_to_occ3d_lut,
)
from renderworld.data.boxes import boxes_frame
from renderworld.data.errors import DatasetError
from renderworld.data.occ3d import Occ3DLabels, load_occ3d_labels
from renderworld.data.occupancy_only import is_occupancy_only, missing_sensor_file_hint
from renderworld.data.table_cache import TableCache
from renderworld.data.tables import check_chain, check_references, read_table
from renderworld.geometry.poses import pose_matrix

__all__ = ["NuScenesReader"]

# child table -> [(column, parent table, empty allowed)]
_REFERENCES: dict[str, list[tuple[str, str, bool]]] = {
    "calibrated_sensor": [("sensor_token", "sensor", False)],
    "instance": [
        ("category_token", "category", False),
        ("first_annotation_token", "sample_annotation", True),
        ("last_annotation_token", "sample_annotation", True),
    ],
    "scene": [
        ("log_token", "log", False),
        ("first_sample_token", "sample", False),
        ("last_sample_token", "sample", False),
    ],
    "sample": [("scene_token", "scene", False)],
    "sample_data": [
        ("sample_token", "sample", False),
        ("ego_pose_token", "ego_pose", False),
        ("calibrated_sensor_token", "calibrated_sensor", False),
    ],
    "sample_annotation": [
        ("sample_token", "sample", False),
        ("instance_token", "instance", False),
        ("visibility_token", "visibility", True),
    ],
    "lidarseg": [("sample_data_token", "sample_data", False)],
}
_CHAINED = ("sample", "sample_data", "sample_annotation")


class NuScenesReader:
    """Read a nuScenes-format dataset with pandas.

    Args:
        dataroot: folder holding ``<version>/``, ``samples/``, ``lidarseg/``, ``gts/`` ...
        version: e.g. ``"v1.0-mini"`` or ``"v1.0-trainval"``.
        cache: keep validated tables as parquet in a user cache folder, so the next load of
            the same, unchanged tables skips JSON parsing and checks (see ``table_cache``).
        cache_dir: cache root (default ``$RENDERWORLD_CACHE_DIR`` or ``~/.cache/renderworld``).

    Raises:
        DatasetError: if the dataroot or version folder is missing, or a required table file
            is absent (checked eagerly; contents load lazily).

    Example:
        >>> r = NuScenesReader("data/mini", "v1.0-mini")
        >>> tok = r.scene_samples("scene-0061")[0]
        >>> pts = r.lidar_points(r.sample_data_token(tok, "LIDAR_TOP"))  # [N, 5] float32
    """

    def __init__(
        self,
        dataroot: str | os.PathLike,
        version: str = "v1.0-mini",
        cache: bool = True,
        cache_dir: str | os.PathLike | None = None,
    ):
        self.dataroot = Path(dataroot)
        self.version = version
        if not self.dataroot.is_dir():
            raise DatasetError(f"dataroot: folder {self.dataroot} does not exist")
        self.version_dir = self.dataroot / version
        if not self.version_dir.is_dir():
            raise DatasetError(f"version: folder {self.version_dir} does not exist")
        missing = [t for t in NUSCENES_TABLES if not (self.version_dir / f"{t}.json").is_file()]
        if missing:
            raise DatasetError(
                f"{self.version_dir}: missing table(s) {', '.join(t + '.json' for t in missing)}"
            )
        self._root_resolved = self.dataroot.resolve()
        self._tables: dict[str, pd.DataFrame] = {}
        self._loading: set[str] = set()
        self._cache = (
            TableCache(self.version_dir, Path(cache_dir) if cache_dir else None) if cache else None
        )

    def __repr__(self) -> str:
        return f"NuScenesReader({str(self.dataroot)!r}, version={self.version!r})"

    # ------------------------------------------------------------------ tables
    @cached_property
    def occupancy_only(self) -> bool:
        """Whether this is a simulated occupancy-only dataset (no sensor files; see
        :mod:`renderworld.data.occupancy_only`)."""
        return is_occupancy_only(self.dataroot)

    @property
    def has_lidarseg(self) -> bool:
        """Whether ``lidarseg.json`` is present."""
        return (self.version_dir / "lidarseg.json").is_file()

    def table(self, name: str) -> pd.DataFrame:
        """Return a table as a DataFrame indexed by token (loaded and checked once).

        Args:
            name: one of the 13 nuScenes tables, or ``"lidarseg"``.
        """
        if name in self._tables:
            return self._tables[name]
        if name not in NUSCENES_TABLES and name != "lidarseg":
            raise ValueError(f"name: unknown table {name!r}; expected one of {NUSCENES_TABLES}")
        cached = self._cache.get(name) if self._cache else None
        if cached is not None:  # validated when it was cached; the key covers every table
            self._tables[name] = cached
            return cached
        df = read_table(self.version_dir, name)
        self._tables[name] = df
        self._loading.add(name)
        try:
            for column, parent, allow_empty in _REFERENCES.get(name, []):
                # A parent that is loading (cycle) has its own check run when it finishes.
                parent_df = self._tables[parent] if parent in self._loading else self.table(parent)
                check_references(df, name, column, parent_df.index, parent, allow_empty)
            if name in _CHAINED:
                check_chain(df, name)
        except DatasetError:
            del self._tables[name]
            raise
        finally:
            self._loading.discard(name)
        if self._cache:
            self._cache.put(name, df)
        return df

    def load_all(self) -> NuScenesReader:
        """Load and check every table now (otherwise they load on first use)."""
        for name in NUSCENES_TABLES:
            self.table(name)
        if self.has_lidarseg:
            self.table("lidarseg")
        _ = self._keyframes
        return self

    # ------------------------------------------------------------------ files
    def path(self, filename: str) -> Path:
        """Resolve a dataset-relative ``filename`` inside the dataroot.

        Raises:
            DatasetError: if the filename is absolute or escapes the dataroot (``../``).
        """
        if not isinstance(filename, str) or not filename:
            raise DatasetError(f"filename: expected a non-empty relative path, got {filename!r}")
        if os.path.isabs(filename):
            raise DatasetError(f"filename {filename!r} is absolute; expected a path in dataroot")
        full = (self.dataroot / filename).resolve()
        if not full.is_relative_to(self._root_resolved):
            raise DatasetError(f"filename {filename!r} escapes the data root {self.dataroot}")
        return full

    def _existing(self, filename: str, what: str) -> Path:
        p = self.path(filename)
        if not p.is_file():
            hint = missing_sensor_file_hint(self.dataroot)
            raise DatasetError(f"{p}: {what} file is missing{hint}")
        return p

    # ------------------------------------------------------------------ scenes and samples
    def scene_names(self) -> list[str]:
        """Scene names in table order."""
        return self.table("scene")["name"].tolist()

    @cached_property
    def _scene_by_name(self) -> dict[str, str]:
        scenes = self.table("scene")
        return dict(zip(scenes["name"], scenes.index, strict=True))

    def scene_token(self, scene: str) -> str:
        """Token of a scene given its name or token."""
        if scene in self._scene_by_name:
            return self._scene_by_name[scene]
        if scene in self.table("scene").index:
            return scene
        raise DatasetError(f"scene.json: no scene named or with token {scene!r}")

    def scene_samples(self, scene: str) -> list[str]:
        """Sample tokens of a scene in time order, following the prev/next chain.

        Raises:
            DatasetError: if the chain leaves the scene, loops, or does not match
                ``nbr_samples`` / ``last_sample_token``.
        """
        token = self.scene_token(scene)
        rec = self.table("scene").loc[token]
        samples = self.table("sample")
        nxt = samples["next"]
        owner = samples["scene_token"]
        out: list[str] = []
        cur = rec["first_sample_token"]
        seen: set[str] = set()
        while cur:
            if cur in seen:
                raise DatasetError(f"sample.json: prev/next chain of scene {rec['name']} loops")
            if owner[cur] != token:
                raise DatasetError(
                    f"sample.json: sample {cur!r} in the chain of scene {rec['name']} belongs to "
                    f"scene {owner[cur]!r}"
                )
            seen.add(cur)
            out.append(cur)
            cur = nxt[cur]
        if out[-1] != rec["last_sample_token"] or len(out) != int(rec["nbr_samples"]):
            raise DatasetError(
                f"scene.json: scene {rec['name']} lists nbr_samples={rec['nbr_samples']} and "
                f"last_sample_token={rec['last_sample_token']!r}, but its sample chain has "
                f"{len(out)} samples ending at {out[-1]!r}"
            )
        return out

    def scene_of_sample(self, sample_token: str) -> str:
        """Scene name of a sample."""
        scene_tok = self._sample_row(sample_token)["scene_token"]
        return self.table("scene").at[scene_tok, "name"]

    def _sample_row(self, sample_token: str) -> pd.Series:
        samples = self.table("sample")
        if sample_token not in samples.index:
            raise DatasetError(f"sample.json: no sample with token {sample_token!r}")
        return samples.loc[sample_token]

    # ------------------------------------------------------------------ sample_data
    @cached_property
    def sd_channel(self) -> pd.Series:
        """Channel name per sample_data token."""
        sd = self.table("sample_data")
        cs_sensor = self.table("calibrated_sensor")["sensor_token"]
        channel = self.table("sensor")["channel"]
        return sd["calibrated_sensor_token"].map(cs_sensor).map(channel)

    @cached_property
    def _keyframes(self) -> dict[tuple[str, str], str]:
        sd = self.table("sample_data")
        key = sd["is_key_frame"].to_numpy(dtype=bool)
        frame = pd.DataFrame(
            {"sample": sd["sample_token"].to_numpy()[key], "ch": self.sd_channel.to_numpy()[key]}
        )
        index = dict(
            zip(zip(frame["sample"], frame["ch"], strict=True), sd.index[key], strict=True)
        )
        samples = self.table("sample").index
        has_lidar = pd.Index(frame.loc[frame["ch"] == LIDAR_NAME, "sample"])
        lacking = samples[~samples.isin(has_lidar)]
        if len(lacking):
            raise DatasetError(
                f"sample_data.json: sample {lacking[0]!r} has no {LIDAR_NAME} keyframe "
                f"({len(lacking)} samples lack one)"
            )
        return index

    def sample_data_token(self, sample_token: str, channel: str) -> str:
        """Keyframe sample_data token of ``channel`` for a sample."""
        try:
            return self._keyframes[(sample_token, channel)]
        except KeyError:
            self._sample_row(sample_token)
            raise DatasetError(
                f"sample_data.json: sample {sample_token!r} has no {channel} keyframe"
            ) from None

    def _sd_row(self, sd_token: str) -> pd.Series:
        sd = self.table("sample_data")
        if sd_token not in sd.index:
            raise DatasetError(f"sample_data.json: no record with token {sd_token!r}")
        return sd.loc[sd_token]

    def sensor_to_ego(self, sd_token: str) -> np.ndarray:
        """[4, 4] sensor→ego transform (calibrated_sensor) of a sample_data record."""
        cs = self.table("calibrated_sensor").loc[self._sd_row(sd_token)["calibrated_sensor_token"]]
        return pose_matrix(cs["translation"], cs["rotation"])

    def ego_to_global(self, sd_token: str) -> np.ndarray:
        """[4, 4] ego→global transform (ego_pose) at a sample_data record's timestamp."""
        ep = self.table("ego_pose").loc[self._sd_row(sd_token)["ego_pose_token"]]
        return pose_matrix(ep["translation"], ep["rotation"])

    def intrinsics(self, sd_token: str) -> np.ndarray:
        """[3, 3] camera intrinsics (pixels) of a camera sample_data record."""
        cs = self.table("calibrated_sensor").loc[self._sd_row(sd_token)["calibrated_sensor_token"]]
        k = np.asarray(cs["camera_intrinsic"], dtype=np.float64)
        if k.shape != (3, 3):
            raise DatasetError(
                f"calibrated_sensor.json: record {cs['token']!r} has camera_intrinsic of shape "
                f"{k.shape}, expected 3x3 (is {sd_token!r} a camera?)"
            )
        return k

    def timestamp(self, sd_token: str) -> int:
        """Timestamp (µs) of a sample_data record."""
        return int(self._sd_row(sd_token)["timestamp"])

    def image_path(self, sd_token: str) -> Path:
        """Existing image file of a camera sample_data record."""
        return self._existing(self._sd_row(sd_token)["filename"], "image")

    # ------------------------------------------------------------------ points and labels
    def lidar_points(self, sd_token: str) -> np.ndarray:
        """[N, 5] float32 points (x, y, z, intensity, ring) in the LiDAR frame.

        Raises:
            DatasetError: naming the file if it is missing or its size is not a multiple of
                5 float32.
        """
        path = self._existing(self._sd_row(sd_token)["filename"], "point cloud")
        size = path.stat().st_size
        if size % 20:
            raise DatasetError(
                f"{path}: {size} bytes is not a multiple of 5 float32 (20 bytes) per point"
            )
        return np.fromfile(path, dtype="<f4").reshape(-1, 5)

    @cached_property
    def _lidarseg_by_sd(self) -> pd.Series:
        if not self.has_lidarseg:
            raise DatasetError(f"{self.version_dir}/lidarseg.json: no lidarseg in this dataset")
        ls = self.table("lidarseg")
        return pd.Series(ls["filename"].to_numpy(), index=ls["sample_data_token"].to_numpy())

    def lidarseg_labels(self, sd_token: str, occ3d: bool = True) -> np.ndarray:
        """[N] uint8 per-point labels of a LIDAR_TOP keyframe.

        Args:
            sd_token: LIDAR_TOP sample_data token.
            occ3d: map the 32 lidarseg classes to Occ3D ids (default) or return them raw.

        Raises:
            DatasetError: naming the file if it is missing, holds labels above 31, or its
                count differs from the point cloud's.
        """
        if sd_token not in self._lidarseg_by_sd.index:
            raise DatasetError(f"lidarseg.json: no lidarseg record for sample_data {sd_token!r}")
        path = self._existing(self._lidarseg_by_sd[sd_token], "lidarseg")
        labels = np.fromfile(path, dtype=np.uint8)
        n_points = self._existing(self._sd_row(sd_token)["filename"], "point cloud").stat()
        n_points = n_points.st_size // 20
        if labels.size != n_points:
            raise DatasetError(
                f"{path}: {labels.size} labels but the point cloud has {n_points} points"
            )
        if labels.size and int(labels.max()) >= len(LIDARSEG_CLASSES):
            raise DatasetError(f"{path}: label {int(labels.max())} is not a lidarseg class 0..31")
        if not occ3d:
            return labels
        return np.asarray(lidarseg_to_occ3d_lut(), dtype=np.uint8)[labels]

    # ------------------------------------------------------------------ annotations
    @cached_property
    def _category_occ3d(self) -> pd.Series:
        cat = self.table("category")
        name_to_occ = {n: LIDARSEG_TO_OCC3D[i] for i, n in enumerate(LIDARSEG_CLASSES)}
        return cat["name"].map(lambda n: name_to_occ.get(n, OTHERS_ID))

    @cached_property
    def _annotations_by_sample(self) -> dict[str, np.ndarray]:
        ann = self.table("sample_annotation")
        groups = ann.groupby("sample_token", sort=False).indices
        return {k: np.asarray(v) for k, v in groups.items()}

    def sample_boxes(self, sample_token: str) -> pd.DataFrame:
        """Annotation boxes of a sample, in the global frame.

        Returns:
            DataFrame with columns token, instance_token, category, occ3d_class, center_x,
            center_y, center_z (m), width, length, height (m), yaw (rad about z),
            num_lidar_pts. Empty (with these columns) when the sample has no annotations.
        """
        self._sample_row(sample_token)
        ann = self.table("sample_annotation")
        rows = ann.iloc[self._annotations_by_sample.get(sample_token, np.zeros(0, int))]
        return boxes_frame(
            rows, self.table("instance"), self.table("category"), self._category_occ3d
        )

    # ------------------------------------------------------------------ Occ3D
    def occ3d_path(self, sample_token: str) -> Path | None:
        """``gts/<scene_name>/<sample_token>/labels.npz`` if it exists, else None."""
        scene = self.scene_of_sample(sample_token)
        p = self.path(f"gts/{scene}/{sample_token}/labels.npz")
        return p if p.is_file() else None

    def occ3d(self, sample_token: str, expected_shape=None) -> Occ3DLabels | None:
        """The sample's Occ3D labels, or None when the dataset has none for it."""
        p = self.occ3d_path(sample_token)
        return None if p is None else load_occ3d_labels(p, expected_shape)
