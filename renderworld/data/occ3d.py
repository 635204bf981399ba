"""Occ3D-nuScenes ground-truth files: ``gts/<scene>/<sample_token>/labels.npz``.

Each file holds ``semantics``, ``mask_lidar`` and ``mask_camera``: uint8 ``[X, Y, Z]``
indexed ``[x, y, z]`` in the ego frame (Occ3D: [200, 200, 16], range
[-40, -40, -1, 40, 40, 5.4] m, 0.4 m). Semantics are Occ3D ids 0..17 (17 = free).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from renderworld.constants import FREE_ID
from renderworld.data.atomic import atomic_write
from renderworld.data.errors import DatasetError

__all__ = ["Occ3DLabels", "load_occ3d_labels", "save_occ3d_labels", "OCC3D_KEYS"]

OCC3D_KEYS = ("semantics", "mask_lidar", "mask_camera")


@dataclass(frozen=True)
class Occ3DLabels:
    """One keyframe's Occ3D ground truth.

    Attributes:
        semantics: [X, Y, Z] uint8 Occ3D class ids (0..17), ego frame.
        mask_lidar: [X, Y, Z] uint8 {0, 1}, voxels observed by LiDAR rays.
        mask_camera: [X, Y, Z] uint8 {0, 1}, voxels observed by the cameras (subset of LiDAR's).
    """

    semantics: np.ndarray
    mask_lidar: np.ndarray
    mask_camera: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        """(X, Y, Z)."""
        return tuple(self.semantics.shape)  # type: ignore[return-value]


def _validate(path: str | os.PathLike, arrays: dict[str, np.ndarray], expected_shape) -> None:
    sem = arrays["semantics"]
    if sem.ndim != 3:
        raise DatasetError(f"{path}: 'semantics' must be 3-D [X, Y, Z], got shape {sem.shape}")
    if expected_shape is not None and tuple(sem.shape) != tuple(expected_shape):
        raise DatasetError(
            f"{path}: 'semantics' has shape {sem.shape}, expected {tuple(expected_shape)}"
        )
    for key in OCC3D_KEYS:
        arr = arrays[key]
        if arr.shape != sem.shape:
            raise DatasetError(f"{path}: {key!r} has shape {arr.shape}, semantics {sem.shape}")
        if arr.dtype not in (np.uint8, np.bool_):
            raise DatasetError(f"{path}: {key!r} must be uint8, got {arr.dtype}")
    if sem.size and int(sem.max()) > FREE_ID:
        raise DatasetError(
            f"{path}: 'semantics' holds class {int(sem.max())}, expected ids 0..{FREE_ID}"
        )
    for key in ("mask_lidar", "mask_camera"):
        if arrays[key].size and int(arrays[key].max()) > 1:
            raise DatasetError(f"{path}: {key!r} must be 0/1, got max {int(arrays[key].max())}")


def load_occ3d_labels(path: str | os.PathLike, expected_shape=None) -> Occ3DLabels:
    """Read and validate an Occ3D ``labels.npz``.

    Args:
        path: the ``.npz`` file.
        expected_shape: optional (X, Y, Z) the arrays must have.

    Returns:
        :class:`Occ3DLabels` with uint8 arrays.

    Raises:
        DatasetError: naming the file when it is missing, not an npz, lacks a key, has a wrong
            shape or dtype, or holds class ids above 17.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: Occ3D labels file not found")
    try:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in OCC3D_KEYS if k not in npz.files]
            if missing:
                raise DatasetError(
                    f"{path}: Occ3D labels lack key(s) {missing}; found {sorted(npz.files)}"
                )
            arrays = {k: npz[k] for k in OCC3D_KEYS}
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise DatasetError(f"{path}: not a readable .npz file ({exc})") from exc
    except ValueError as exc:
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(f"{path}: not a readable .npz file ({exc})") from exc
    _validate(path, arrays, expected_shape)
    return Occ3DLabels(*(arrays[k].astype(np.uint8, copy=False) for k in OCC3D_KEYS))


def save_occ3d_labels(
    path: str | os.PathLike,
    semantics: np.ndarray,
    mask_lidar: np.ndarray,
    mask_camera: np.ndarray,
) -> Path:
    """Write an Occ3D ``labels.npz`` atomically (temp file + rename).

    Args:
        path: destination ``.npz``; parent folders are created.
        semantics: [X, Y, Z] class ids 0..17.
        mask_lidar: [X, Y, Z] 0/1.
        mask_camera: [X, Y, Z] 0/1.

    Returns:
        The written path.
    """
    arrays = {
        "semantics": np.asarray(semantics),
        "mask_lidar": np.asarray(mask_lidar),
        "mask_camera": np.asarray(mask_camera),
    }
    for key, arr in arrays.items():
        if arr.dtype.kind not in "uib":
            raise ValueError(f"{key}: expected an integer or bool array, got {arr.dtype}")
        arrays[key] = arr.astype(np.uint8)
    try:
        _validate(path, arrays, None)
    except DatasetError as exc:
        raise ValueError(str(exc)) from None
    return atomic_write(path, lambda tmp: np.savez_compressed(tmp, **arrays), ".tmp.npz")
