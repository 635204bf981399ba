"""Sensor rig (vehicle n015, docs/formats.md#sensors-and-calibration) and the 32-beam LiDAR.

LiDAR frame: x right, y forward, z up (nuScenes LIDAR_TOP). Camera frame: z forward, x right,
y down. ``calibrated_sensor`` poses are sensor→ego; intrinsics are given at 1600x900 and
scaled to the written image size (fx, cx by W/1600; fy, cy by H/900).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import CAMERA_NAMES, LIDAR_NAME
from renderworld.geometry import pose_matrix, scale_intrinsics

__all__ = [
    "CALIBRATION",
    "SensorRig",
    "lidar_beams",
    "camera_time_offsets",
    "FULL_SIZE",
    "xform",
    "rotate",
]

FULL_SIZE = (1600, 900)

#: channel -> (translation [3] m, rotation [w, x, y, z], (fx, cx, cy) at 1600x900 or None).
CALIBRATION: dict[str, tuple[tuple, tuple, tuple | None]] = {
    LIDAR_NAME: ((0.9437, 0.0, 1.8402), (0.70780, -0.00649, 0.01065, -0.70631), None),
    "CAM_FRONT": ((1.7008, 0.0160, 1.5110), (0.49980, -0.50303, 0.49978, -0.49737),
                  (1266.4, 816.3, 491.5)),
    "CAM_FRONT_RIGHT": ((1.5509, -0.4934, 1.4958), (0.20603, -0.20269, 0.68245, -0.67136),
                        (1260.8, 808.0, 495.3)),
    "CAM_FRONT_LEFT": ((1.5239, 0.4946, 1.5093), (0.67573, -0.67363, 0.21214, -0.21123),
                       (1272.6, 826.6, 479.8)),
    "CAM_BACK": ((0.0283, 0.0035, 1.5791), (0.50379, -0.49740, -0.49419, 0.50455),
                 (809.2, 829.2, 481.8)),
    "CAM_BACK_LEFT": ((1.0357, 0.4848, 1.5910), (0.69242, -0.70316, -0.11648, 0.11203),
                      (1256.7, 792.1, 492.8)),
    "CAM_BACK_RIGHT": ((1.0149, -0.4806, 1.5624), (0.12281, -0.13240, -0.70043, 0.69050),
                       (1259.5, 807.3, 501.2)),
}  # fmt: skip


def rotate(mat: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v @ mat[:3, :3].T`` for vectors [N, 3] without BLAS (fast for tall thin arrays)."""
    r = np.asarray(mat)[:3, :3]
    return np.stack(
        [v[:, 0] * r[i, 0] + v[:, 1] * r[i, 1] + v[:, 2] * r[i, 2] for i in range(3)], 1
    )


def xform(mat: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a [4, 4] rigid transform to points [N, 3]."""
    return rotate(mat, p) + np.asarray(mat)[:3, 3]


def lidar_beams() -> np.ndarray:
    """Elevation angles [32] radians of the HDL-32E beams, ring 0 lowest (-30.67° .. +10.67°)."""
    return np.deg2rad(np.linspace(-30.67, 10.67, 32))


@dataclass
class SensorRig:
    """Calibrations and intrinsics at a given image size.

    Attributes:
        width, height: written image size, pixels.
        sensor_to_ego: channel -> [4, 4] float64.
        intrinsics: camera channel -> [3, 3] float64 at ``width`` x ``height``.
    """

    width: int
    height: int
    sensor_to_ego: dict[str, np.ndarray]
    intrinsics: dict[str, np.ndarray]

    @classmethod
    def build(cls, width: int, height: int) -> SensorRig:
        """The n015 rig (docs/formats.md#sensors-and-calibration).

        Intrinsics are scaled to ``width`` x ``height``.
        """
        if width <= 0 or height <= 0:
            raise ValueError(f"image size: expected positive width/height, got {width}x{height}")
        s2e, intr = {}, {}
        for ch, (t, q, k) in CALIBRATION.items():
            s2e[ch] = pose_matrix(t, q)
            if k is not None:
                full = np.array([[k[0], 0.0, k[1]], [0.0, k[0], k[2]], [0.0, 0.0, 1.0]])
                intr[ch] = scale_intrinsics(full, width / FULL_SIZE[0], height / FULL_SIZE[1])
        return cls(width, height, s2e, intr)

    def pixel_rays(self, channel: str, width: int, height: int) -> np.ndarray:
        """Unit ray directions [H*W, 3] (camera frame) through pixel centres (i + 0.5, j + 0.5)
        of a ``width`` x ``height`` image of this camera (intrinsics rescaled to that size)."""
        key = (channel, width, height)
        cache = self.__dict__.setdefault("_rays", {})
        if key in cache:
            return cache[key]
        K = scale_intrinsics(self.intrinsics[channel], width / self.width, height / self.height)
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        d = d.reshape(-1, 3)
        cache[key] = d / np.linalg.norm(d, axis=1, keepdims=True)
        return cache[key]


def camera_time_offsets(rig: SensorRig) -> dict[str, int]:
    """Microseconds from the LiDAR keyframe timestamp to each camera's exposure.

    The LiDAR spins once per 50 ms (20 Hz, clockwise seen from above) starting, at its
    keyframe timestamp, from the gap between CAM_FRONT_LEFT and CAM_BACK_LEFT (ego yaw 80°);
    each camera fires as the sweep crosses its optical axis, so offsets lie in (0, 50) ms.
    """
    out = {}
    start = np.deg2rad(80.0)
    for ch in CAMERA_NAMES:
        axis = rig.sensor_to_ego[ch][:3, 2]  # camera z in ego
        yaw = float(np.arctan2(axis[1], axis[0]))
        frac = np.mod(start - yaw, 2 * np.pi) / (2 * np.pi)
        out[ch] = int(round(frac * 50_000))
    return out
