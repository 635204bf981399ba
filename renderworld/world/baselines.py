"""Baselines reported beside every world model (docs/protocol.md#baselines-and-references).

* :func:`copy_paste_forecast` - every future frame is the current frame.
* :func:`warp_constant_velocity_forecast` - the current frame resampled into each future ego
  frame assuming the last displacement repeats and the heading stays fixed.
* :func:`constant_velocity_trajectory` - the last displacement repeated, cumulated.
* :func:`constant_turn_rate_poses` / :func:`constant_turn_rate_trajectory` - the last
  displacement and the last heading change repeated (history only).
* :func:`warp_along_poses` - the current frame resampled into future ego frames given their
  poses (x, y, yaw): with constant-turn-rate poses the "CTR-warp" baseline; with the
  ground-truth future poses the "GT-pose warp" reference (an upper bound for a static world
  that uses the future, never a competitor).

Displacements follow :mod:`renderworld.world.config`: ``d[i]`` = frame i -> i+1 in metres, in
the current ego frame (x forward, y left). Inputs may be numpy arrays or torch tensors; the
output has the input's type (and device).
"""

from __future__ import annotations

import numpy as np
import torch

from renderworld.constants import FREE_ID, FUTURE_FRAMES, OCC3D_GRID, GridSpec

__all__ = [
    "constant_turn_rate_poses",
    "constant_turn_rate_trajectory",
    "constant_velocity_trajectory",
    "warp_along_poses",
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


def _wrap_angle(a: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.sin(a), torch.cos(a))


def constant_turn_rate_poses(history_poses, steps: int = FUTURE_FRAMES):
    """Future poses repeating the last displacement and the last heading change.

    With ``d`` the last displacement (frame t-1 -> t, current ego frame) and ``w`` the last
    heading change (yaw_t - yaw_{t-1}), step j (1..S) moves by ``R(j w) d`` and turns by ``w``:
    ``p_k = sum_{j<=k} R(j w) d``, ``yaw_k = k w``. With ``w = 0`` this is the constant-velocity
    trajectory with the heading fixed. Uses the history only.

    Args:
        history_poses: [T, 3] or [B, T, 3] (x, y, yaw) of frames t-T+1..t in the current ego
            frame (metres, radians; the last row is the current frame, zeros), T >= 2.
        steps: S future frames.

    Returns:
        [S, 3] or [B, S, 3] float (x, y, yaw) of frames t+1..t+S in the current ego frame.
    """
    p, was_np = _as_torch(history_poses, "history_poses")
    _check_steps(steps)
    if p.dim() not in (2, 3) or p.shape[-1] != 3 or p.shape[-2] < 2:
        raise ValueError(
            f"history_poses: expected [T>=2, 3] or [B, T>=2, 3] (x, y, yaw), got {tuple(p.shape)}"
        )
    if not torch.isfinite(p.double()).all():
        raise ValueError("history_poses: expected finite values")
    dtype = p.dtype if p.is_floating_point() else torch.float64
    q = p.to(torch.float64)
    d = q[..., -1, :2] - q[..., -2, :2]  # [..., 2]
    w = _wrap_angle(q[..., -1, 2] - q[..., -2, 2])  # [...]
    j = torch.arange(1, steps + 1, dtype=torch.float64, device=p.device)
    ang = w[..., None] * j  # [..., S]
    c, s = torch.cos(ang), torch.sin(ang)
    step_x = c * d[..., None, 0] - s * d[..., None, 1]
    step_y = s * d[..., None, 0] + c * d[..., None, 1]
    out = torch.stack([step_x.cumsum(-1), step_y.cumsum(-1), _wrap_angle(ang)], dim=-1)
    out = out.to(dtype)
    return out.numpy() if was_np else out


def constant_turn_rate_trajectory(history_poses, steps: int = FUTURE_FRAMES):
    """Constant-turn-rate plan: positions of :func:`constant_turn_rate_poses`.

    Args:
        history_poses: [T, 3] or [B, T, 3] (x, y, yaw), current ego frame, T >= 2.
        steps: S future frames.

    Returns:
        [S, 2] or [B, S, 2] metres, positions of frames t+1..t+S in the current ego frame.
    """
    poses = constant_turn_rate_poses(history_poses, steps)
    return poses[..., :2].copy() if isinstance(poses, np.ndarray) else poses[..., :2].clone()


def warp_along_poses(occupancy, poses, grid: GridSpec = OCC3D_GRID, fill: int = FREE_ID):
    """Resample a frame into other ego frames whose poses in it are known.

    Each target voxel centre ``c`` (x, y in target frame k) is mapped to the source frame as
    ``R(yaw_k) c + (x_k, y_k)`` and takes the label of the source voxel containing it
    (nearest-neighbour in BEV, same z level); sources outside the grid give ``fill``.

    Args:
        occupancy: [X, Y, Z] or [B, X, Y, Z] labels (any dtype) in the source ego frame,
            indexed on ``grid``.
        poses: [S, 3] or [B, S, 3] (x, y, yaw) of each target frame in the source frame
            (metres, radians).
        grid: the grid of the occupancy (x/y range and voxel size are used).
        fill: label of target voxels whose source lies outside the grid.

    Returns:
        [S, X, Y, Z] or [B, S, X, Y, Z], the dtype of ``occupancy``.
    """
    occ, was_np = _as_torch(occupancy, "occupancy")
    pz, _ = _as_torch(poses, "poses")
    batched = occ.dim() == 4
    if occ.dim() not in (3, 4) or tuple(occ.shape[-3:]) != tuple(grid.shape):
        raise ValueError(
            f"occupancy: expected [(B,) {', '.join(map(str, grid.shape))}] on grid "
            f"{grid.name!r}, got {tuple(occ.shape)}"
        )
    nb = occ.shape[0] if batched else 1
    if pz.dim() != (3 if batched else 2) or pz.shape[-1] != 3 or (batched and pz.shape[0] != nb):
        want = "[B, S, 3]" if batched else "[S, 3]"
        raise ValueError(f"poses: expected {want} (x, y, yaw), got {tuple(pz.shape)}")
    if pz.shape[-2] < 1:
        raise ValueError("poses: expected at least one target frame, got 0")
    if not torch.isfinite(pz.double()).all():
        raise ValueError("poses: expected finite values")
    occ_b = occ if batched else occ[None]
    p = (pz if batched else pz[None]).to(device=occ.device, dtype=torch.float64)
    nx, ny, _ = grid.shape
    sx, sy = grid.voxel_size[0], grid.voxel_size[1]
    x0, y0 = grid.range_min[0], grid.range_min[1]
    cx = x0 + (torch.arange(nx, dtype=torch.float64, device=occ.device) + 0.5) * sx
    cy = y0 + (torch.arange(ny, dtype=torch.float64, device=occ.device) + 0.5) * sy
    gx, gy = cx[:, None], cy[None, :]  # [X, 1], [1, Y]
    c = torch.cos(p[..., 2])[..., None, None]  # [B, S, 1, 1]
    s = torch.sin(p[..., 2])[..., None, None]
    src_x = c * gx - s * gy + p[..., 0, None, None]  # [B, S, X, Y]
    src_y = s * gx + c * gy + p[..., 1, None, None]
    ix = torch.floor((src_x - x0) / sx).long()
    iy = torch.floor((src_y - y0) / sy).long()
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    ix, iy = ix.clamp(0, nx - 1), iy.clamp(0, ny - 1)
    bi = torch.arange(nb, device=occ.device)[:, None, None, None]
    out = occ_b[bi, ix, iy]  # [B, S, X, Y, Z]
    out = torch.where(inside[..., None], out, torch.full_like(out, fill))
    out = out if batched else out[0]
    return out.numpy() if was_np else out
