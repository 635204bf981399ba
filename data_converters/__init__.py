"""nuScenes-format dataset -> RenderWorld infos (parquet) and LiDAR-projected 2-D labels.

Entry point: :func:`create_data` (``tools/create_data.py`` wraps it). The pieces are public for
tests and reuse: trajectories (``trajectory``; the command rule is
:func:`renderworld.world.ego.command_from_trajectory`), LiDAR -> image label maps
(``projection``, ``labels``), scene splits (``splits``), info rows (``sample_infos``).
"""

from data_converters.convert import ConvertOptions, ConvertSummary, create_data, default_out_dir
from data_converters.labels import make_labels, point_sources, sweep_tokens
from data_converters.projection import (
    STATIC_CLASS_IDS,
    CameraView,
    PointSource,
    label_maps,
    project_to_label_map,
)
from data_converters.splits import assign_splits, load_split_lists
from data_converters.trajectory import (
    boxes_in_ego_frame,
    ego_future,
    ego_history,
    relative_positions,
)

__all__ = [
    "STATIC_CLASS_IDS",
    "CameraView",
    "ConvertOptions",
    "ConvertSummary",
    "PointSource",
    "assign_splits",
    "boxes_in_ego_frame",
    "create_data",
    "default_out_dir",
    "ego_future",
    "ego_history",
    "label_maps",
    "load_split_lists",
    "make_labels",
    "point_sources",
    "project_to_label_map",
    "relative_positions",
    "sweep_tokens",
]
