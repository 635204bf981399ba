"""An independent LiDAR -> image label oracle from the raw JSON records (no package geometry).

Follows the devkit's ``map_pointcloud_to_image`` step by step (lidar -> ego -> global at the LiDAR
time -> ego at the camera time -> camera), with quaternions written out by hand, then the
label-resolution pixel rule and a dictionary z-buffer.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from renderworld.constants import LIDARSEG_TO_OCC3D


def quat_to_mat(q) -> np.ndarray:
    """Rotation from a [w, x, y, z] quaternion, written out."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def load_raw(root: Path, version: str) -> dict:
    """{table: {token: record}} for the tables the oracle needs."""
    names = ("sample_data", "calibrated_sensor", "ego_pose", "sensor", "lidarseg", "sample")
    return {
        n: {r["token"]: r for r in json.loads((Path(root) / version / f"{n}.json").read_text())}
        for n in names
    }


def keyframe_record(raw: dict, sample_token: str, channel: str) -> dict:
    """The keyframe sample_data record of ``channel`` for a sample."""
    sensor = {s["token"]: s["channel"] for s in raw["sensor"].values()}
    cs = {c["token"]: sensor[c["sensor_token"]] for c in raw["calibrated_sensor"].values()}
    return next(
        r
        for r in raw["sample_data"].values()
        if r["sample_token"] == sample_token
        and r["is_key_frame"]
        and cs[r["calibrated_sensor_token"]] == channel
    )


def oracle_labels(root: Path, raw: dict, sample_token: str, channel: str, label_hw=None) -> dict:
    """{(u, v): (depth, occ3d label)} for one camera at label size ``label_hw`` (default full)."""
    lidar = keyframe_record(raw, sample_token, "LIDAR_TOP")
    cam = keyframe_record(raw, sample_token, channel)
    pts = np.fromfile(Path(root) / lidar["filename"], "<f4").reshape(-1, 5)[:, :3].astype(float)
    seg_file = next(r for r in raw["lidarseg"].values() if r["sample_data_token"] == lidar["token"])
    seg = np.fromfile(Path(root) / seg_file["filename"], np.uint8)
    p = pts
    for rec, inverse in (
        (raw["calibrated_sensor"][lidar["calibrated_sensor_token"]], False),
        (raw["ego_pose"][lidar["ego_pose_token"]], False),
        (raw["ego_pose"][cam["ego_pose_token"]], True),
        (raw["calibrated_sensor"][cam["calibrated_sensor_token"]], True),
    ):
        rot, t = quat_to_mat(rec["rotation"]), np.asarray(rec["translation"], float)
        p = (p - t) @ rot if inverse else p @ rot.T + t
    k = np.asarray(raw["calibrated_sensor"][cam["calibrated_sensor_token"]]["camera_intrinsic"])
    uvw = p @ k.T
    u, v, d = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2], p[:, 2]
    w, h = cam["width"], cam["height"]
    lh, lw = label_hw if label_hw is not None else (h, w)
    keep = (d > 1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out: dict = {}
    for i in np.flatnonzero(keep):
        key = (int(np.floor(u[i] * lw / w)), int(np.floor(v[i] * lh / h)))
        if key not in out or d[i] < out[key][0]:
            out[key] = (d[i], LIDARSEG_TO_OCC3D[int(seg[i])])
    return out


def as_dict(labels) -> dict:
    """{(u, v): (depth, label)} of a SparseLabels2D."""
    return {
        (int(a), int(b)): (float(x), int(y))
        for a, b, x, y in zip(labels.u, labels.v, labels.depth, labels.label)
    }
