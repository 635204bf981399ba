"""Sparse LiDAR-projected 2-D labels: per camera (u, v, depth, label), one ``.npz`` per sample.

A label map of camera ``c`` has ``height x width`` pixels (the *label resolution*). Each stored
point is the nearest LiDAR return of its pixel (z-buffer): ``u`` column, ``v`` row (uint16
pixel indices at the label resolution), ``depth`` camera z in metres (float32) and ``label`` an
Occ3D class id 0..16, or :data:`IGNORE_LABEL` when the point carries no semantics (a LiDAR sweep
without lidarseg). Densified maps use depth 0 and label :data:`IGNORE_LABEL` where no point falls.

File layout (``np.savez_compressed``, no pickles): ``cameras`` [C] str, ``height`` [C] int32,
``width`` [C] int32, ``params`` 0-d str (JSON of the settings that made it), and for each camera
index ``c``: ``cam{c}_u``, ``cam{c}_v`` uint16 [M_c], ``cam{c}_depth`` float32 [M_c],
``cam{c}_label`` uint8 [M_c].
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from renderworld.constants import IGNORE_LABEL
from renderworld.data.atomic import atomic_write
from renderworld.data.errors import DatasetError

__all__ = [
    "IGNORE_LABEL",
    "SparseLabels2D",
    "zbuffer_nearest",
    "densify_labels2d",
    "save_labels2d",
    "load_labels2d",
    "read_labels2d_params",
]

_MAX_PIXEL = np.iinfo(np.uint16).max


@dataclass(frozen=True)
class SparseLabels2D:
    """One camera's sparse label map.

    Attributes:
        u: [M] uint16 pixel columns at the label resolution.
        v: [M] uint16 pixel rows.
        depth: [M] float32 camera z (metres), > 0.
        label: [M] uint8 Occ3D ids 0..16 or :data:`IGNORE_LABEL`.
        height: label map height (pixels).
        width: label map width (pixels).
    """

    u: np.ndarray
    v: np.ndarray
    depth: np.ndarray
    label: np.ndarray
    height: int
    width: int

    def __len__(self) -> int:
        return int(self.u.shape[0])

    def densify(self, size: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Dense maps, see :func:`densify_labels2d`."""
        return densify_labels2d(self, size)


def zbuffer_nearest(pixel: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Indices of the nearest point of each distinct pixel (a z-buffer), vectorised.

    Args:
        pixel: [N] integer flat pixel index of each point.
        depth: [N] depth of each point (smaller wins; ties keep the earlier point).

    Returns:
        [P] int64 indices into the inputs, one per distinct pixel, sorted by pixel.
    """
    pixel = np.asarray(pixel)
    depth = np.asarray(depth)
    if pixel.shape != depth.shape or pixel.ndim != 1:
        raise ValueError(
            f"pixel/depth: expected two [N] arrays of equal length, got {pixel.shape} "
            f"and {depth.shape}"
        )
    if pixel.size == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((depth, pixel))  # by pixel, then depth; stable for ties
    sorted_pix = pixel[order]
    first = np.empty(order.size, dtype=bool)
    first[0] = True
    np.not_equal(sorted_pix[1:], sorted_pix[:-1], out=first[1:])
    return order[first].astype(np.int64, copy=False)


def densify_labels2d(
    labels: SparseLabels2D, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Dense depth and semantic maps of one camera.

    Args:
        labels: the sparse labels.
        size: optional (H, W) output size. Pixel ``(u, v)`` of the label resolution goes to
            ``(floor((u + 0.5) W / width), floor((v + 0.5) H / height))`` and the nearest point
            per output pixel is kept. For integer down-scaling factors this equals projecting at
            the output size directly (``floor(floor(x) / k) == floor(x / k)``); for other
            factors it is a pixel-centre approximation.

    Returns:
        ``(depth [H, W] float32 metres (0 = no point), semantics [H, W] uint8 (255 = ignore))``.
    """
    h, w = labels.height, labels.width
    u = labels.u.astype(np.int64)
    v = labels.v.astype(np.int64)
    depth_pts = labels.depth
    label_pts = labels.label
    if size is not None:
        oh, ow = int(size[0]), int(size[1])
        if oh <= 0 or ow <= 0:
            raise ValueError(f"size: expected positive (H, W), got {size}")
        if (oh, ow) != (h, w):
            u = np.floor((u + 0.5) * (ow / w)).astype(np.int64)
            v = np.floor((v + 0.5) * (oh / h)).astype(np.int64)
            keep = zbuffer_nearest(v * ow + u, depth_pts)
            u, v, depth_pts, label_pts = u[keep], v[keep], depth_pts[keep], label_pts[keep]
        h, w = oh, ow
    depth = np.zeros((h, w), dtype=np.float32)
    sem = np.full((h, w), IGNORE_LABEL, dtype=np.uint8)
    depth[v, u] = depth_pts
    sem[v, u] = label_pts
    return depth, sem


def _check_camera(name: str, lab: SparseLabels2D) -> None:
    n = lab.u.shape[0]
    for key, dtype in (("u", np.uint16), ("v", np.uint16), ("depth", np.float32)):
        arr = getattr(lab, key)
        if arr.shape != (n,) or arr.dtype != dtype:
            raise ValueError(
                f"labels[{name}].{key}: expected [{n}] {np.dtype(dtype)}, got {arr.shape} "
                f"{arr.dtype}"
            )
    if lab.label.shape != (n,) or lab.label.dtype != np.uint8:
        raise ValueError(f"labels[{name}].label: expected [{n}] uint8, got {lab.label.dtype}")
    if not (0 < lab.height <= _MAX_PIXEL and 0 < lab.width <= _MAX_PIXEL):
        raise ValueError(f"labels[{name}]: size {lab.height}x{lab.width} outside 1..{_MAX_PIXEL}")
    if n and (int(lab.u.max()) >= lab.width or int(lab.v.max()) >= lab.height):
        raise ValueError(f"labels[{name}]: pixel outside the {lab.height}x{lab.width} map")


def save_labels2d(
    path: str | os.PathLike,
    cameras: list[str] | tuple[str, ...],
    labels: list[SparseLabels2D],
    params: dict | None = None,
) -> Path:
    """Write one sample's sparse labels atomically (temp file + rename).

    Args:
        path: destination ``.npz``; parent folders are created.
        cameras: [C] camera names, in the order of ``labels``.
        labels: [C] sparse labels.
        params: JSON-serialisable settings stored beside the arrays (for re-run checks).

    Returns:
        The written path.
    """
    if len(cameras) != len(labels):
        raise ValueError(
            f"cameras/labels: expected equal lengths, got {len(cameras)} and {len(labels)}"
        )
    arrays: dict[str, np.ndarray] = {
        "cameras": np.asarray(list(cameras), dtype=str),
        "height": np.asarray([lab.height for lab in labels], dtype=np.int32),
        "width": np.asarray([lab.width for lab in labels], dtype=np.int32),
        "params": np.asarray(json.dumps(params or {}, sort_keys=True)),
    }
    for c, (name, lab) in enumerate(zip(cameras, labels)):
        _check_camera(name, lab)
        arrays[f"cam{c}_u"] = lab.u
        arrays[f"cam{c}_v"] = lab.v
        arrays[f"cam{c}_depth"] = lab.depth
        arrays[f"cam{c}_label"] = lab.label
    return atomic_write(path, lambda tmp: np.savez_compressed(tmp, **arrays), ".tmp.npz")


def _open(path: Path):
    if not path.is_file():
        raise DatasetError(f"{path}: 2-D labels file not found")
    try:
        return np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise DatasetError(f"{path}: not a readable .npz file ({exc})") from exc


def read_labels2d_params(path: str | os.PathLike) -> dict:
    """The ``params`` dict stored in a labels file (reads only that entry).

    Raises:
        DatasetError: naming the file if it is missing or unreadable.
    """
    path = Path(path)
    with _open(path) as npz:
        if "params" not in npz.files:
            raise DatasetError(f"{path}: 2-D labels file lacks 'params'")
        try:
            return json.loads(str(npz["params"]))
        except (ValueError, zipfile.BadZipFile, OSError) as exc:
            raise DatasetError(f"{path}: unreadable 'params' ({exc})") from exc


def load_labels2d(path: str | os.PathLike) -> tuple[list[str], list[SparseLabels2D]]:
    """Read one sample's sparse labels.

    Returns:
        ``(cameras [C] names, labels [C])``.

    Raises:
        DatasetError: naming the file if it is missing, unreadable or inconsistent.
    """
    path = Path(path)
    with _open(path) as npz:
        try:
            cameras = [str(c) for c in npz["cameras"]]
            height, width = npz["height"], npz["width"]
            out = []
            for c in range(len(cameras)):
                out.append(
                    SparseLabels2D(
                        npz[f"cam{c}_u"],
                        npz[f"cam{c}_v"],
                        npz[f"cam{c}_depth"],
                        npz[f"cam{c}_label"],
                        int(height[c]),
                        int(width[c]),
                    )
                )
        except KeyError as exc:
            raise DatasetError(f"{path}: 2-D labels file lacks {exc}") from None
        except (zipfile.BadZipFile, OSError, EOFError, ValueError, IndexError) as exc:
            raise DatasetError(f"{path}: corrupt 2-D labels file ({exc})") from exc
    for name, lab in zip(cameras, out):
        try:
            _check_camera(name, lab)
        except ValueError as exc:
            raise DatasetError(f"{path}: {exc}") from None
    return cameras, out
