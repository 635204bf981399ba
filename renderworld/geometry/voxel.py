"""Voxel grids in the ego frame.

A grid covers ``[range_min, range_max)`` per axis with ``shape`` voxels, indexed
``[x, y, z]``. Voxel centre = ``range_min + (i + 0.5) * voxel_size`` (docs/conventions.md#grids).
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import GridSpec

__all__ = ["VoxelGrid"]


class VoxelGrid:
    """Index arithmetic for an axis-aligned voxel grid.

    Args:
        spec: the grid's range and shape (see :class:`renderworld.constants.GridSpec`).

    Example:
        >>> from renderworld.constants import OCC3D_GRID
        >>> g = VoxelGrid(OCC3D_GRID)
        >>> g.index_to_centre(np.array([[0, 0, 0]]))
        array([[-39.8, -39.8, -0.8]])
    """

    def __init__(self, spec: GridSpec):
        if len(spec.shape) != 3 or min(spec.shape) <= 0:
            raise ValueError(f"spec.shape: expected 3 positive sizes, got {spec.shape}")
        if any(hi <= lo for lo, hi in zip(spec.range_min, spec.range_max)):
            raise ValueError(
                f"spec: range_max must exceed range_min per axis, got "
                f"{spec.range_min} .. {spec.range_max}"
            )
        self.spec = spec
        self.shape = tuple(int(s) for s in spec.shape)
        self.range_min = np.asarray(spec.range_min, dtype=np.float64)
        self.range_max = np.asarray(spec.range_max, dtype=np.float64)
        self.voxel_size = (self.range_max - self.range_min) / np.asarray(self.shape)

    def __repr__(self) -> str:
        return (
            f"VoxelGrid(shape={self.shape}, range_min={self.range_min.tolist()}, "
            f"range_max={self.range_max.tolist()}, voxel_size={self.voxel_size.tolist()})"
        )

    def centres(self) -> np.ndarray:
        """All voxel centres, [X, Y, Z, 3] float64, metres, ego frame."""
        axes = [
            self.range_min[a] + (np.arange(self.shape[a]) + 0.5) * self.voxel_size[a]
            for a in range(3)
        ]
        grid = np.meshgrid(*axes, indexing="ij")
        return np.stack(grid, axis=-1)

    def index_to_centre(self, index):
        """Voxel centre of integer indices.

        Args:
            index: [..., 3] integer (i, j, k); numpy or torch.

        Returns:
            [..., 3] float centres, metres (float64 numpy, or float32 torch).
        """
        if type(index).__module__.startswith("torch"):
            import torch

            lo = torch.as_tensor(self.range_min, dtype=torch.float32, device=index.device)
            sz = torch.as_tensor(self.voxel_size, dtype=torch.float32, device=index.device)
            return lo + (index.float() + 0.5) * sz
        return self.range_min + (np.asarray(index) + 0.5) * self.voxel_size

    def points_to_index(self, points):
        """Voxel index of points and whether each lies inside the grid.

        A point exactly on ``range_max`` is outside (half-open ranges).

        Args:
            points: [..., 3] metres, ego frame; numpy or torch.

        Returns:
            ``(index [..., 3] int64, inside [..., bool])``; indices of outside points are
            clipped into range so they can be used for gathering, but must be masked.
        """
        if points.shape[-1] != 3:
            raise ValueError(f"points: expected shape [..., 3], got {tuple(points.shape)}")
        if type(points).__module__.startswith("torch"):
            import torch

            lo = torch.as_tensor(self.range_min, dtype=points.dtype, device=points.device)
            sz = torch.as_tensor(self.voxel_size, dtype=points.dtype, device=points.device)
            shape = torch.as_tensor(self.shape, device=points.device)
            idx = torch.floor((points - lo) / sz).long()
            inside = ((idx >= 0) & (idx < shape)).all(-1) & torch.isfinite(points).all(-1)
            idx = torch.minimum(idx.clamp_min(0), shape - 1)
            return idx, inside
        pts = np.asarray(points, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            rel = np.floor((pts - self.range_min) / self.voxel_size)
        finite = np.isfinite(rel).all(-1)
        rel = np.where(np.isfinite(rel), rel, -1)
        idx = rel.astype(np.int64)
        shape = np.asarray(self.shape)
        inside = ((idx >= 0) & (idx < shape)).all(-1) & finite
        idx = np.clip(idx, 0, shape - 1)
        return idx, inside

    def flat_index(self, index):
        """Row-major flat index ``(i * Y + j) * Z + k`` of [..., 3] integer indices."""
        _, y, z = self.shape
        return (index[..., 0] * y + index[..., 1]) * z + index[..., 2]
