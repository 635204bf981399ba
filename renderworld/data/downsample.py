"""Down-sampling Occ3D occupancy to coarser grids of the same range (integer factors).

Rule (docs/conventions.md#grids): a coarse voxel is occupied if any of its fine voxels is non-free;
its class is the most frequent non-free class among its fine voxels (ties -> lower id); otherwise it
is free (``FREE_ID``). A coarse voxel of a mask is observed if any fine voxel is observed.
So a one-voxel-thick road layer survives down-sampling in z, as the planner and the collision
metric need.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES, GridSpec

__all__ = ["downsample_occupancy", "downsample_mask", "grid_factor"]


def _factors(factor, ndim: int) -> tuple[int, int, int]:
    if isinstance(factor, (int, np.integer)):
        f = (int(factor),) * 3
    else:
        f = tuple(int(x) for x in factor)
        if len(f) != 3 or any(int(x) != x for x in factor):
            raise ValueError(f"factor: expected an int or 3 ints (fx, fy, fz), got {factor!r}")
    if any(x < 1 for x in f):
        raise ValueError(f"factor: expected positive integers, got {factor!r}")
    if ndim < 3:
        raise ValueError(f"semantics: expected [..., X, Y, Z], got {ndim} dimensions")
    return f  # type: ignore[return-value]


def _blocks(arr: np.ndarray, f: tuple[int, int, int], name: str) -> np.ndarray:
    """[..., X, Y, Z] -> [..., X/fx, Y/fy, Z/fz, fx*fy*fz]."""
    *lead, x, y, z = arr.shape
    if x % f[0] or y % f[1] or z % f[2]:
        raise ValueError(f"{name}: shape {arr.shape[-3:]} is not divisible by factor {f}")
    b = arr.reshape(*lead, x // f[0], f[0], y // f[1], f[1], z // f[2], f[2])
    n = len(lead)
    perm = (*range(n), n, n + 2, n + 4, n + 1, n + 3, n + 5)
    return b.transpose(perm).reshape(*lead, x // f[0], y // f[1], z // f[2], f[0] * f[1] * f[2])


def downsample_occupancy(semantics: np.ndarray, factor) -> np.ndarray:
    """Down-sample class ids by the occupancy rule (any non-free wins; mode, ties -> lower id).

    Args:
        semantics: [..., X, Y, Z] integer Occ3D ids 0..17 (17 = free).
        factor: int or (fx, fy, fz) dividing X, Y, Z.

    Returns:
        [..., X/fx, Y/fy, Z/fz] uint8 class ids.

    Raises:
        ValueError: on non-integer input, ids outside 0..17 or shapes not divisible by factor.
    """
    semantics = np.asarray(semantics)
    f = _factors(factor, semantics.ndim)
    if semantics.dtype.kind not in "ui":
        raise ValueError(f"semantics: expected integer class ids, got dtype {semantics.dtype}")
    if semantics.size and (int(semantics.min()) < 0 or int(semantics.max()) > FREE_ID):
        raise ValueError(
            f"semantics: expected ids 0..{FREE_ID}, got range "
            f"{int(semantics.min())}..{int(semantics.max())}"
        )
    if f == (1, 1, 1):
        return semantics.astype(np.uint8)
    blocks = _blocks(semantics, f, "semantics")
    out_shape = blocks.shape[:-1]
    blocks = blocks.reshape(-1, blocks.shape[-1])
    out = np.full(blocks.shape[0], FREE_ID, dtype=np.uint8)
    occupied = np.flatnonzero((blocks != FREE_ID).any(axis=1))  # most cells are all free
    if occupied.size:
        sub = blocks[occupied].astype(np.int32)
        sub += (np.arange(occupied.size, dtype=np.int32) * NUM_OCC3D_CLASSES)[:, None]
        counts = np.bincount(sub.ravel(), minlength=occupied.size * NUM_OCC3D_CLASSES)
        counts = counts.reshape(occupied.size, NUM_OCC3D_CLASSES)[:, :FREE_ID]  # non-free 0..16
        out[occupied] = counts.argmax(axis=1)  # first maximum -> lower id on ties
    return out.reshape(out_shape)


def downsample_mask(mask: np.ndarray, factor) -> np.ndarray:
    """Down-sample a visibility mask: a coarse voxel is observed if any fine voxel is.

    Args:
        mask: [..., X, Y, Z] bool or 0/1 integers.
        factor: int or (fx, fy, fz).

    Returns:
        [..., X/fx, Y/fy, Z/fz] bool.
    """
    mask = np.asarray(mask)
    f = _factors(factor, mask.ndim)
    if mask.dtype.kind not in "uib":
        raise ValueError(f"mask: expected a bool or integer array, got dtype {mask.dtype}")
    if f == (1, 1, 1):
        return mask.astype(bool)
    return _blocks(mask.astype(bool), f, "mask").any(axis=-1)


def grid_factor(fine_shape, grid: GridSpec) -> tuple[int, int, int]:
    """Integer factors from a fine [X, Y, Z] shape to ``grid.shape``.

    Raises:
        ValueError: if some axis of ``grid`` does not divide the fine shape.
    """
    fine = tuple(int(x) for x in fine_shape)
    if len(fine) != 3 or any(a % b for a, b in zip(fine, grid.shape)):
        raise ValueError(
            f"grid: {grid.name} shape {grid.shape} is not an integer down-sampling of {fine}"
        )
    return tuple(a // b for a, b in zip(fine, grid.shape))  # type: ignore[return-value]
