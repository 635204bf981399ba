"""Shared pieces of the infos datasets: grid resolution, infos loading, scene bookkeeping."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
from torch.utils.data import Dataset

from renderworld.constants import OCC3D_GRID, GridSpec, get_grid
from renderworld.data.downsample import downsample_mask, downsample_occupancy, grid_factor
from renderworld.data.errors import DatasetError
from renderworld.data.infos import load_infos, stack_column
from renderworld.data.occ3d import load_occ3d_labels

__all__ = ["resolve_grid", "check_size", "InfosDataset"]


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


def check_size(name: str, value) -> tuple[int, int] | None:
    """``value`` as a positive (H, W) pair (None passes through); ValueError naming ``name``."""
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


class InfosDataset(Dataset):
    """Base of the infos datasets: the sorted infos, LiDAR-time ego poses, scene positions.

    Attributes:
        infos: DataFrame sorted by (scene_index, frame_index).
        ego2global: [N, 4, 4] float64 ego poses at the LiDAR keyframe timestamps.
        scene_first: [N] row of each row's scene's first keyframe.
        scene_count: [N] keyframes in each row's scene.
        text: {column: [N] str} of the string columns.
    """

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
        # Plain lists for per-item access (DataFrame.at costs more than the rest of an item).
        names = ["sample_token", "scene_name", "occ_path", "labels2d_path", "command"]
        names += ["scene_description"] if "scene_description" in self.infos.columns else []
        names += [c for c in self.infos.columns if c.startswith("cam") and c.endswith("_path")]
        self.text = {name: self.infos[name].astype(str).tolist() for name in names}

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
