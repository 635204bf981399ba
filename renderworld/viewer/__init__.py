"""3-D scene recordings for the Rerun viewer (the optional extra ``renderworld[viz]``).

``write_scene_recording(data_root, "scene.rrd", scene=..., img2occ=..., tokenizer=...,
planner=...)`` writes one scene: the six cameras (frusta, calibrated poses, images), LiDAR
points coloured by class, Occ3D GT occupancy, agent and ego boxes, and, when their models are
given, Img2Occ's Gaussians and read-out occupancy, the tokenizer's reconstruction, the world
model's forecasts and the planned vs GT trajectories, on ``frame`` / ``time`` timelines.
Open the file with ``rerun scene.rrd`` or ``rerun --web-viewer scene.rrd``.

Importing this package does not import Rerun (only writing a recording does) nor torch (the
recording module loads on first use, so the main job's own process stays light); the rest of
RenderWorld never imports it.
"""

from renderworld.viewer._rerun import INSTALL_HINT, rerun_available
from renderworld.viewer.job import main_job_recording, report_section, view_command
from renderworld.viewer.voxels import (
    VoxelBoxes,
    gaussian_arrays,
    grid_for_shape,
    hidden_voxels,
    occupancy_boxes,
)

__all__ = [
    "DATA_LAYERS",
    "INSTALL_HINT",
    "LAYERS",
    "MODEL_LAYERS",
    "RecordingSummary",
    "VoxelBoxes",
    "gaussian_arrays",
    "grid_for_shape",
    "hidden_voxels",
    "main_job_recording",
    "occupancy_boxes",
    "report_section",
    "rerun_available",
    "view_command",
    "write_scene_recording",
]

_LAZY = {"DATA_LAYERS", "LAYERS", "MODEL_LAYERS", "RecordingSummary", "write_scene_recording"}


def __getattr__(name: str):
    # The recording module imports torch (through the model layers): load it on first use.
    if name in _LAZY:
        from renderworld.viewer import recording

        return getattr(recording, name)
    raise AttributeError(f"module 'renderworld.viewer' has no attribute {name!r}")
