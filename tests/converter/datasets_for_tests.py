"""Small converted datasets shared by the converter and dataset tests (builder-made).

Each builder dataset has all six cameras; the "moving" ones drive a continuous path sampled at
every sensor's own timestamp, so the LiDAR-time -> camera-time chain matters.
"""

from __future__ import annotations

from pathlib import Path

from data_converters import ConvertOptions, create_data
from renderworld.constants import CAMERA_NAMES
from tests.data.builder import VERSION, build_tiny_dataset

__all__ = ["VERSION", "build", "build_and_convert"]


def build(root: Path, **kwargs) -> Path:
    """A six-camera builder dataset (kwargs override the builder's options)."""
    opts = dict(num_samples=8, num_points=1500, cameras=CAMERA_NAMES, point_range=(2.0, 40.0))
    opts.update(kwargs)
    build_tiny_dataset(root, **opts)
    return root


def build_and_convert(root: Path, options: ConvertOptions | None = None, **kwargs) -> Path:
    """Build then convert (progress bars off); returns the output folder."""
    build(root, **kwargs)
    options = options or ConvertOptions(progress=False)
    return create_data(root, VERSION, options=options).out_dir
