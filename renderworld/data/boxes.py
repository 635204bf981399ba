"""Annotation boxes of a nuScenes sample as one flat table (global frame).

``NuScenesReader.sample_boxes`` selects a sample's ``sample_annotation`` rows; this module turns
them into the columns the converter and the collision metric read.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = ["BOX_COLUMNS", "boxes_frame", "yaw_from_quaternions"]

#: Columns of :func:`boxes_frame`, in order.
BOX_COLUMNS = (
    "token",
    "instance_token",
    "instance_index",
    "category",
    "occ3d_class",
    "center_x",
    "center_y",
    "center_z",
    "width",
    "length",
    "height",
    "yaw",
    "num_lidar_pts",
)


def yaw_from_quaternions(q: np.ndarray) -> np.ndarray:
    """Yaw (rad) about z of [N, 4] quaternions [w, x, y, z]."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def boxes_frame(
    rows: pd.DataFrame, instance: pd.DataFrame, category: pd.DataFrame, category_occ3d: pd.Series
) -> pd.DataFrame:
    """Flatten ``sample_annotation`` rows into one box per row.

    Args:
        rows: ``sample_annotation`` records (columns token, instance_token, translation [3] m,
            size [3] = width, length, height m, rotation [4] w, x, y, z, num_lidar_pts).
        instance: the ``instance`` table indexed by token (column category_token).
        category: the ``category`` table indexed by token (column name).
        category_occ3d: Occ3D class id per category token.

    Returns:
        DataFrame with :data:`BOX_COLUMNS`: centre (m) and yaw (rad about z) in the global frame,
        sizes in metres, ``instance_index`` the row of the box's instance in ``instance`` (the
        same number for the same road user in every sample). Empty (with these columns) when
        ``rows`` is empty.
    """
    cat_tok = rows["instance_token"].map(instance["category_token"])
    centre = np.asarray(rows["translation"].tolist(), dtype=np.float64).reshape(-1, 3)
    size = np.asarray(rows["size"].tolist(), dtype=np.float64).reshape(-1, 3)
    quat = np.asarray(rows["rotation"].tolist(), dtype=np.float64).reshape(-1, 4)
    return pd.DataFrame(
        {
            "token": rows["token"].to_numpy(),
            "instance_token": rows["instance_token"].to_numpy(),
            "instance_index": instance.index.get_indexer(rows["instance_token"]).astype(np.int64),
            "category": cat_tok.map(category["name"]).to_numpy(),
            "occ3d_class": cat_tok.map(category_occ3d).to_numpy(dtype=np.int64),
            "center_x": centre[:, 0],
            "center_y": centre[:, 1],
            "center_z": centre[:, 2],
            "width": size[:, 0],
            "length": size[:, 1],
            "height": size[:, 2],
            "yaw": yaw_from_quaternions(quat),
            "num_lidar_pts": rows["num_lidar_pts"].to_numpy(dtype=np.int64),
        },
        columns=list(BOX_COLUMNS),
    )
