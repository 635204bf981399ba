"""Occupancy-only datasets: simulated nuScenes-format datasets without sensor files.

The simulator's ``mode=occupancy`` (:mod:`renderworld.sim.modes`) writes the 13 tables, maps
and the Occ3D labels but no camera image, LiDAR point file or lidarseg; its run report
``<dataroot>/sim_report.json`` holds ``"mode": "occupancy"``. Such a dataset serves the
tokenizer and the world model (occupancy, ego poses, boxes, commands) but not Img2Occ or the
2-D labels, which need the images and the LiDAR.
"""

from __future__ import annotations

import json
from pathlib import Path

from renderworld.data.errors import DatasetError

__all__ = ["SIM_REPORT_NAME", "is_occupancy_only", "missing_sensor_file_hint"]

#: The simulator's run report at the dataset root (``renderworld.sim.REPORT_NAME``).
SIM_REPORT_NAME = "sim_report.json"


def is_occupancy_only(dataroot) -> bool:
    """Whether ``dataroot`` is a simulated occupancy-only dataset (no sensor files).

    Args:
        dataroot: dataset folder.

    Returns:
        True when ``<dataroot>/sim_report.json`` exists and its ``mode`` is ``"occupancy"``;
        False without a report (a recorded or full simulated dataset).

    Raises:
        DatasetError: naming the report when it is not a JSON object.
    """
    path = Path(dataroot) / SIM_REPORT_NAME
    if not path.is_file():
        return False
    try:
        report = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: not a readable JSON run report ({exc})") from exc
    if not isinstance(report, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(report).__name__}")
    return report.get("mode") == "occupancy"


def missing_sensor_file_hint(dataroot) -> str:
    """Text to append to a "file is missing" error: why, when the dataset is occupancy-only."""
    if not is_occupancy_only(dataroot):
        return ""
    return (
        f" (this is an occupancy-only dataset: {Path(dataroot) / SIM_REPORT_NAME} says mode "
        "'occupancy', so it has no camera images, LiDAR point files or lidarseg; it serves "
        "the tokenizer and world model, not Img2Occ or the 2-D labels)"
    )
