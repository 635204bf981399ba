"""nuScenes-format data: table reader, Occ3D label io, infos, 2-D labels and torch datasets."""

from renderworld.data.downsample import downsample_mask, downsample_occupancy
from renderworld.data.errors import DatasetError
from renderworld.data.infos import load_infos
from renderworld.data.labels2d import (
    IGNORE_LABEL,
    SparseLabels2D,
    densify_labels2d,
    load_labels2d,
    save_labels2d,
)
from renderworld.data.occ3d import Occ3DLabels, load_occ3d_labels, save_occ3d_labels
from renderworld.data.reader import NuScenesReader

__all__ = [
    "IGNORE_LABEL",
    "DatasetError",
    "Img2OccDataset",
    "NuScenesReader",
    "Occ3DLabels",
    "OccSequenceDataset",
    "SparseLabels2D",
    "densify_labels2d",
    "downsample_mask",
    "downsample_occupancy",
    "load_infos",
    "load_labels2d",
    "load_occ3d_labels",
    "save_labels2d",
    "save_occ3d_labels",
]

_LAZY = {"Img2OccDataset", "OccSequenceDataset"}


def __getattr__(name: str):
    # The torch datasets load lazily so that the reader (and the simulator) stay torch-free.
    if name in _LAZY:
        from renderworld.data import datasets

        return getattr(datasets, name)
    raise AttributeError(f"module 'renderworld.data' has no attribute {name!r}")
