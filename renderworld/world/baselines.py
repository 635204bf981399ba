"""Baselines reported beside every world model (DESIGN.md §4).

* :func:`copy_paste_forecast` - every future frame is the current frame.
* :func:`warp_constant_velocity_forecast` - the current frame resampled into each future ego
  frame assuming the last displacement repeats and the heading stays fixed.
* :func:`constant_velocity_trajectory` - the last displacement repeated, cumulated.

Displacements follow :mod:`renderworld.world.config`: ``d[i]`` = frame i -> i+1 in metres, in
the current ego frame (x forward, y left). Inputs may be numpy arrays or torch tensors; the
output has the input's type (and device).
"""

from __future__ import annotations

import numpy as np
import torch

from renderworld.constants import FREE_ID, FUTURE_FRAMES, OCC3D_GRID, GridSpec

__all__ = [
    "constant_velocity_trajectory",
    "copy_paste_forecast",
    "warp_constant_velocity_forecast",
]


def _as_torch(x, name: str) -> tuple[torch.Tensor, bool]:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x), True
    if isinstance(x, torch.Tensor):
        return x, False
    raise TypeError(f"{name}: expected a numpy array or torch tensor, got {type(x).__name__}")


def _check_steps(steps: int) -> None:
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")


def copy_paste_forecast(occupancy, steps: int = FUTURE_FRAMES):
    """Repeat the current frame.

    Args:
        occupancy: [X, Y, Z] or [B, X, Y, Z] uint8 labels of the current frame.
        steps: S future frames.

    Returns:
        [S, X, Y, Z] or [B, S, X, Y, Z], same dtype (a copy, never a view of the input).
    """
    occ, was_np = _as_torch(occupancy, "occupancy")
    _check_steps(steps)
    if occ.dim() not in (3, 4):
        raise ValueError(f"occupancy: expected [X, Y, Z] or [B, X, Y, Z], got {tuple(occ.shape)}")
    out = occ.unsqueeze(-4).expand(*occ.shape[:-3], steps, *occ.shape[-3:]).clone()
    return out.numpy() if was_np else out


def constant_velocity_trajectory(displacements, steps: int = FUTURE_FRAMES):
    """Constant-velocity plan: the last history displacement repeated.

    Args:
        displacements: [T-1, 2] or [B, T-1, 2] metres (T-1 >= 1), current ego frame.
        steps: S future frames.

    Returns:
        [S, 2] or [B, S, 2] metres: positions ``k * d[-1]`` (k = 1..S), current ego frame.
    """
    d, was_np = _as_torch(displacements, "displacements")
    _check_steps(steps)
    if d.dim() not in (2, 3) or d.shape[-1] != 2 or d.shape[-2] < 1:
        raise ValueError(
            f"displacements: expected [T-1>=1, 2] or [B, T-1, 2], got {tuple(d.shape)}"
        )
    k = torch.arange(1, steps + 1, dtype=d.dtype, device=d.device)
    out = d[..., -1:, :] * k[:, None]
    return out.numpy() if was_np else out


def warp_constant_velocity_forecast(
    occupancy, last_displacement, steps: int = FUTURE_FRAMES, grid: GridSpec = OCC3D_GRID
):
    """Current frame resampled into each future ego frame under constant velocity.

    Future frame k (1..S) is assumed to have its origin at ``k * last_displacement`` in the
    current ego frame and the current heading (no rotation: constant velocity, not constant
    turn rate). Each future voxel centre is mapped into the current frame and takes the label
    of the current-frame voxel containing it (nearest-neighbour in BEV, same z level). Voxels
    whose source lies outside the grid are set to free (``FREE_ID``): nothing is known there,
    and free is what an unobserved Occ3D voxel usually stores.

    Args:
        occupancy: [X, Y, Z] or [B, X, Y, Z] uint8, current ego frame, indexed on ``grid``.
        last_displacement: [2] or [B, 2] metres, ``d[t-1]`` in the current ego frame.
        steps: S future frames.
        grid: the grid the occupancy lives on (only x/y range and voxel size are used).

    Returns:
        [S, X, Y, Z] or [B, S, X, Y, Z], same dtype as ``occupancy``.
    """
    occ, was_np = _as_torch(occupancy, "occupancy")
    d, _ = _as_torch(last_displacement, "last_displacement")
    _check_steps(steps)
    batched = occ.dim() == 4
    if occ.dim() not in (3, 4) or tuple(occ.shape[-3:]) != tuple(grid.shape):
        raise ValueError(
            f"occupancy: expected [(B,) {', '.join(map(str, grid.shape))}] on grid "
            f"{grid.name!r}, got {tuple(occ.shape)}"
        )
    want = (occ.shape[0], 2) if batched else (2,)
    if tuple(d.shape) != want:
        raise ValueError(f"last_displacement: expected {list(want)}, got {tuple(d.shape)}")
    if not torch.isfinite(d.double()).all():
        raise ValueError("last_displacement: expected finite values")
    occ_b = occ if batched else occ[None]
    d_b = (d if batched else d[None]).to(device=occ.device, dtype=torch.float64)
    nb = occ_b.shape[0]
    nx, ny, _ = grid.shape
    sx, sy = grid.voxel_size[0], grid.voxel_size[1]
    x0, y0 = grid.range_min[0], grid.range_min[1]
    cx = x0 + (torch.arange(nx, dtype=torch.float64, device=occ.device) + 0.5) * sx
    cy = y0 + (torch.arange(ny, dtype=torch.float64, device=occ.device) + 0.5) * sy
    k = torch.arange(1, steps + 1, dtype=torch.float64, device=occ.device)
    # Source position in the current frame of each future voxel centre: [B, S, X] / [B, S, Y].
    src_x = cx[None, None] + (k[None, :, None] * d_b[:, None, None, 0])
    src_y = cy[None, None] + (k[None, :, None] * d_b[:, None, None, 1])
    ix = torch.floor((src_x - x0) / sx).long()
    iy = torch.floor((src_y - y0) / sy).long()
    ok = (ix >= 0) & (ix < nx), (iy >= 0) & (iy < ny)
    ix, iy = ix.clamp(0, nx - 1), iy.clamp(0, ny - 1)
    bi = torch.arange(nb, device=occ.device)[:, None, None, None]
    out = occ_b[bi, ix[:, :, :, None], iy[:, :, None, :]]  # [B, S, X, Y, Z]
    inside = ok[0][:, :, :, None] & ok[1][:, :, None, :]
    out = torch.where(inside[..., None], out, torch.full_like(out, FREE_ID))
    out = out if batched else out[0]
    return out.numpy() if was_np else out
