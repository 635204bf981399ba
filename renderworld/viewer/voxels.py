"""Occupancy volumes and Gaussians as flat arrays for the viewer (numpy only, no Rerun).

Only occupied voxels become boxes: a full Occ3D grid has 640 000 voxels of which typically
5-20 % are occupied, and a viewer stays responsive with instanced boxes for those alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import FREE_ID, GRIDS, OCC3D_COLORS, OCC3D_GRID, GridSpec

__all__ = ["VoxelBoxes", "occupancy_boxes", "grid_for_shape", "gaussian_arrays", "hidden_voxels"]


@dataclass(frozen=True)
class VoxelBoxes:
    """Occupied voxels of one volume as instanced boxes.

    Attributes:
        centres: [M, 3] float32 voxel centres, metres, in the volume's (ego) frame.
        half_size: [3] float32 half the voxel edge lengths, metres (shared by all boxes).
        classes: [M] uint16 Occ3D class ids (0..16; free voxels are never included).
    """

    centres: np.ndarray
    half_size: np.ndarray
    classes: np.ndarray


def grid_for_shape(shape) -> GridSpec:
    """The Occ3D-range grid of an [X, Y, Z] volume shape (a named grid when one matches).

    Raises:
        ValueError: when ``shape`` is not three positive integers.
    """
    try:
        dims = tuple(int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape: expected [X, Y, Z] integers, got {shape!r}") from None
    if len(dims) != 3 or min(dims) < 1:
        raise ValueError(f"shape: expected [X, Y, Z] positive integers, got {shape!r}")
    for spec in (OCC3D_GRID, *GRIDS.values()):
        if tuple(spec.shape) == dims:
            return spec
    return GridSpec("x".join(map(str, dims)), OCC3D_GRID.range_min, OCC3D_GRID.range_max, dims)


def hidden_voxels(occupied: np.ndarray) -> np.ndarray:
    """[X, Y, Z] bool: occupied voxels whose six face neighbours are all occupied.

    Such a voxel cannot be seen from any viewpoint (every face touches another box), so
    leaving it out changes no picture. Outside the grid counts as free: a voxel on the grid's
    border is never hidden.
    """
    occ = np.asarray(occupied, dtype=bool)
    pad = np.pad(occ, 1, constant_values=False)
    hidden = occ.copy()
    x, y, z = occ.shape
    for axis in range(3):
        for step in (-1, 1):
            lo = [slice(1, x + 1), slice(1, y + 1), slice(1, z + 1)]
            lo[axis] = slice(1 + step, occ.shape[axis] + 1 + step)
            hidden &= pad[tuple(lo)]
    return hidden


def occupancy_boxes(
    occupancy: np.ndarray,
    grid: GridSpec | None = None,
    mask: np.ndarray | None = None,
    surface_only: bool = False,
) -> VoxelBoxes:
    """The occupied (non-free) voxels of a semantic volume as boxes.

    Args:
        occupancy: [X, Y, Z] integer Occ3D ids (0..17, ``FREE_ID`` = 17 free), ego frame,
            indexed [x, y, z] (docs/conventions.md#grids).
        grid: its grid (default: the Occ3D-range grid of that shape).
        mask: optional [X, Y, Z] bool/{0,1}: keep only voxels where it is set (e.g. the
            camera mask).
        surface_only: leave out :func:`hidden_voxels` (decided before ``mask`` applies), which
            no viewpoint shows; about half of a full Occ3D frame (solid buildings, ground).

    Returns:
        :class:`VoxelBoxes`; centre = range_min + (i + 0.5) · voxel size.

    Raises:
        ValueError: wrong ranks or shapes, class ids above 17.
    """
    occ = np.asarray(occupancy)
    if occ.ndim != 3:
        raise ValueError(f"occupancy: expected [X, Y, Z], got shape {occ.shape}")
    if occ.size and int(occ.max()) > FREE_ID:
        raise ValueError(f"occupancy: expected class ids 0..{FREE_ID}, got max {int(occ.max())}")
    spec = grid_for_shape(occ.shape) if grid is None else grid
    if tuple(spec.shape) != occ.shape:
        raise ValueError(f"grid: shape {tuple(spec.shape)} does not match occupancy {occ.shape}")
    keep = occ != FREE_ID
    if surface_only:
        keep &= ~hidden_voxels(keep)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != occ.shape:
            raise ValueError(f"mask: expected shape {occ.shape}, got {m.shape}")
        keep &= m.astype(bool)
    idx = np.flatnonzero(keep)
    ijk = np.stack(np.unravel_index(idx, occ.shape), axis=1).astype(np.float32)
    lo = np.asarray(spec.range_min, dtype=np.float32)
    size = (np.asarray(spec.range_max, dtype=np.float32) - lo) / np.asarray(occ.shape, np.float32)
    return VoxelBoxes(
        centres=lo + (ijk + 0.5) * size,
        half_size=(size / 2).astype(np.float32),
        classes=occ.reshape(-1)[idx].astype(np.uint16),
    )


def gaussian_arrays(means, quats, scales, opacities, logits, min_opacity: float = 0.0) -> dict:
    """One sample's Gaussians as numpy arrays, the faint ones dropped.

    Args:
        means: [V, 3] metres, ego frame.
        quats: [V, 4] unit quaternions ``[w, x, y, z]``.
        scales: [V, 3] standard deviations, metres.
        opacities: [V] in (0, 1).
        logits: [V, K] semantic logits over the K = 17 non-free classes.
        min_opacity: keep Gaussians with opacity >= this (0 keeps all).

    Returns:
        dict with ``centres`` [N, 3] float32, ``quats_xyzw`` [N, 4] float32 (Rerun's order),
        ``scales`` [N, 3] float32, ``opacity`` [N] float32, ``classes`` [N] uint16 (argmax),
        ``rgba`` [N, 4] uint8 (class colour, alpha = opacity).

    Raises:
        ValueError: mismatched shapes or ``min_opacity`` outside [0, 1].
    """
    arrays = [np.asarray(_numpy(a), dtype=np.float32) for a in (means, quats, scales, opacities)]
    means, quats, scales, opac = arrays
    logits = np.asarray(_numpy(logits), dtype=np.float32)
    v = means.shape[0]
    for name, a, shape in (
        ("means", means, (v, 3)),
        ("quats", quats, (v, 4)),
        ("scales", scales, (v, 3)),
        ("opacities", opac, (v,)),
    ):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {list(shape)}, got {list(a.shape)}")
    if logits.ndim != 2 or logits.shape[0] != v:
        raise ValueError(f"logits: expected shape [{v}, K], got {list(logits.shape)}")
    if not 0.0 <= float(min_opacity) <= 1.0:
        raise ValueError(f"min_opacity: expected a value in [0, 1], got {min_opacity!r}")
    keep = opac >= float(min_opacity)
    classes = logits[keep].argmax(axis=1).astype(np.uint16)
    rgba = np.empty((int(keep.sum()), 4), dtype=np.uint8)
    rgba[:, :3] = np.asarray(OCC3D_COLORS, dtype=np.uint8)[classes]
    rgba[:, 3] = np.clip(np.rint(opac[keep] * 255), 0, 255).astype(np.uint8)
    return {
        "centres": means[keep],
        "quats_xyzw": quats[keep][:, [1, 2, 3, 0]],
        "scales": scales[keep],
        "opacity": opac[keep],
        "classes": classes,
        "rgba": rgba,
    }


def _numpy(x):
    return x.detach().float().cpu().numpy() if hasattr(x, "detach") else x
