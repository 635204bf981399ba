"""Sensor settings of a simulation (:class:`SensorSpec`) and the checks scene descriptions share.

Kept apart from :mod:`renderworld.sim.scene` (which re-exports :class:`SensorSpec`) so that
each module stays small; this module imports nothing of the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["SensorSpec", "check_int", "spec_error"]


def spec_error(name: str, expected: str, got: Any) -> ValueError:
    """``ValueError("<name>: expected <expected>, got <got>")``."""
    return ValueError(f"{name}: expected {expected}, got {got!r}")


def check_int(name: str, value: Any, lo: int) -> int:
    """``value`` if it is an integer (not a bool) >= ``lo``; else ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise spec_error(name, f"an integer >= {lo}", value)
    return value


@dataclass
class SensorSpec:
    """Sensor settings shared by all scenes.

    Attributes:
        image_width: written image width, pixels (intrinsics scale by width / 1600).
        image_height: written image height, pixels (intrinsics scale by height / 900).
        lidar_azimuth_steps: LiDAR rays per beam per revolution (1084 ~ HDL-32E at 20 Hz).
        lidar_range: maximum LiDAR range, metres.
        lidar_range_sigma: range noise (metres) when ``lidar_noise`` is on.
        lidar_dropout: fraction of returns dropped when ``lidar_noise`` is on.
        jpeg_quality: JPEG quality (1..95).
        mask_camera_scale: resolution of the depth maps used for ``mask_camera``, as a fraction
            of the written image size.
    """

    image_width: int = 400
    image_height: int = 225
    lidar_azimuth_steps: int = 1084
    lidar_range: float = 70.0
    lidar_range_sigma: float = 0.02
    lidar_dropout: float = 0.05
    jpeg_quality: int = 90
    mask_camera_scale: float = 0.5

    def validate(self) -> None:
        for f in ("image_width", "image_height"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise spec_error(f"sensors.{f}", "a positive integer image size", v)
        check_int("sensors.lidar_azimuth_steps", self.lidar_azimuth_steps, 16)
        if not (1 <= self.jpeg_quality <= 95):
            raise spec_error("sensors.jpeg_quality", "1..95", self.jpeg_quality)
        if not (0.0 < self.mask_camera_scale <= 1.0):
            raise spec_error(
                "sensors.mask_camera_scale", "a fraction in (0, 1]", self.mask_camera_scale
            )
        if not (0.0 <= self.lidar_dropout < 1.0):
            raise spec_error("sensors.lidar_dropout", "a fraction in [0, 1)", self.lidar_dropout)
        if not (self.lidar_range > 0 and self.lidar_range_sigma >= 0):
            raise spec_error(
                "sensors.lidar_range", "positive range and sigma >= 0", self.lidar_range
            )
