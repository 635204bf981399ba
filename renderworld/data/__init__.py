"""nuScenes-format data: table reader, Occ3D label io (torch datasets come with the converter)."""

from renderworld.data.errors import DatasetError
from renderworld.data.occ3d import Occ3DLabels, load_occ3d_labels, save_occ3d_labels
from renderworld.data.reader import NuScenesReader

__all__ = [
    "DatasetError",
    "NuScenesReader",
    "Occ3DLabels",
    "load_occ3d_labels",
    "save_occ3d_labels",
]
