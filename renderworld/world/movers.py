"""Forecasts that move other road users: the object constant-velocity baseline and a reference.

* :func:`object_constant_velocity_forecast` - the "object-CV warp" baseline (history only):
  the current frame without its movers carried along constant-turn-rate ego poses, plus each
  movable bird's-eye-view component of the current frame shifted by its own velocity, measured
  against an earlier history frame brought into the current frame.
* :func:`gt_pose_movers_reference` - "GT-pose + object-CV movers" (reads the future poses: a
  reference, never a competitor): the current frame with its movers moved by a history-only
  rule (default :func:`object_cv_frames`) warped along the ground-truth future poses, the
  forecast a pose-warp model with that rule would give if its ego poses were perfect.
* :func:`gt_movers_reference` - "GT-pose warp + GT movers" (reads the future: an upper bound,
  never a competitor): the current frame without its movers warped along the ground-truth
  future poses, with the ground-truth future movers pasted in.

Movers are the voxels of :data:`~renderworld.constants.MOVABLE_CLASS_IDS`. A component is a
set of bird's-eye-view cells holding one movable class at some height, connected through
edges or corners (8-connectivity: at coarse voxels a yawed car rasterises along a diagonal).

Velocity matching rule (:func:`object_velocities`): the components of the current frame and
of frame ``t - lag`` are compared in the current ego frame (the past centroids moved by that
frame's pose, so the ego's own motion is compensated and a parked car keeps its place). Each
current component takes the nearest past component of the same class within a gate of
``max_speed * lag * dt`` metres, one to one, closest pairs first (greedy assignment): two
nearby cars cannot both claim the same past car, and a new or unmatched object keeps zero
velocity (it stays where it is in the world). A shift shorter than ``min_shift_voxels``
voxels is taken as zero: at coarse voxels the centroid of a parked car jitters by a fraction
of a voxel as the ego moves, and a velocity made of that jitter would smear parked cars.

Frames follow :mod:`renderworld.world.baselines`: poses are (x, y, yaw) of a frame in the
current ego frame (x forward, y left; metres, radians). Inputs may be numpy arrays or torch
tensors; outputs have the type (and device) of the occupancy input.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy import ndimage

from renderworld.constants import (
    FREE_ID,
    FUTURE_FRAMES,
    KEYFRAME_DT,
    MOVABLE_CLASS_IDS,
    OCC3D_CLASSES,
    OCC3D_GRID,
    GridSpec,
)
from renderworld.world.baselines import _as_torch, constant_turn_rate_poses, warp_along_poses

__all__ = [
    "MAX_SPEED_MPS",
    "MOVERS",
    "MoversFrames",
    "bev_components",
    "gt_movers_reference",
    "gt_pose_movers_reference",
    "movable_mask",
    "object_constant_velocity_forecast",
    "object_cv_frames",
    "object_velocities",
    "paste_shifted",
    "remove_movers",
    "warp_frames_along_poses",
]

#: How a pose-warp forecast moves other road users (``stage.movers``): ``static`` (nothing
#: moves), ``object_cv`` (:func:`object_cv_frames`) or ``learned`` (the model's mover head,
#: :mod:`renderworld.world.learned_movers`).
MOVERS = ("static", "object_cv", "learned")

#: Gate of the velocity matching, metres per second, per movable class (default: vehicles).
MAX_SPEED_MPS: dict[int, float] = {cls: 15.0 for cls in MOVABLE_CLASS_IDS} | {
    OCC3D_CLASSES.index("pedestrian"): 3.0
}
_EIGHT = np.ones((3, 3), dtype=bool)
#: How the movers of a forecast move, history only: ``movers_frames(history_occupancy
#: [B, T, X, Y, Z], history_poses [B, T, 3] float64, steps, grid)`` -> [B, S, X, Y, Z], frame k
#: the current frame with its movers where they are k steps later, still in the current ego
#: frame (as :func:`object_cv_frames`).
MoversFrames = Callable[[torch.Tensor, torch.Tensor, int, GridSpec], torch.Tensor]


def movable_mask(occupancy: torch.Tensor) -> torch.Tensor:
    """Bool mask, shape of ``occupancy`` (integer labels): voxels of a movable class."""
    ids = torch.tensor(MOVABLE_CLASS_IDS, device=occupancy.device)
    return torch.isin(occupancy.long(), ids)


def remove_movers(occupancy: torch.Tensor, fill: int = FREE_ID) -> torch.Tensor:
    """A copy of ``occupancy`` (any shape, integer labels) with movable voxels set to ``fill``."""
    return torch.where(movable_mask(occupancy), torch.full_like(occupancy, fill), occupancy)


def bev_components(frame: np.ndarray, grid: GridSpec) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Movable bird's-eye-view components of one frame.

    Args:
        frame: [X, Y, Z] integer labels, indexed on ``grid``.
        grid: the frame's grid (x/y range and voxel size are used).

    Returns:
        One (class id, cells [X, Y] bool, centroid [2] metres in the frame's ego frame) per
        8-connected component of each movable class's BEV footprint.
    """
    out = []
    sx, sy = grid.voxel_size[0], grid.voxel_size[1]
    for cls in MOVABLE_CLASS_IDS:
        bev = (frame == cls).any(axis=-1)
        if not bev.any():
            continue
        labels, n = ndimage.label(bev, structure=_EIGHT)
        for j, box in enumerate(ndimage.find_objects(labels), start=1):  # bounding boxes
            cells = np.zeros(bev.shape, dtype=bool)
            cells[box] = labels[box] == j
            ix, iy = np.nonzero(cells[box])
            ix, iy = ix + box[0].start, iy + box[1].start
            c = np.array([grid.range_min[0] + (ix.mean() + 0.5) * sx,
                          grid.range_min[1] + (iy.mean() + 0.5) * sy])  # fmt: skip
            out.append((cls, cells, c))
    return out


def object_velocities(
    current: list,
    past: list,
    past_pose,
    lag_s: float,
    grid: GridSpec,
    min_shift_voxels: float = 1.0,
) -> np.ndarray:
    """Velocity of each current component from its match in a past frame (module rule).

    Args:
        current: :func:`bev_components` of the current frame.
        past: :func:`bev_components` of the past frame (centroids in its own ego frame).
        past_pose: [3] (x, y, yaw) of the past frame in the current ego frame.
        lag_s: seconds between the two frames (> 0).
        grid: the grid (voxel size for ``min_shift_voxels``).
        min_shift_voxels: shifts shorter than this many x-voxels over ``lag_s`` count as zero.

    Returns:
        [N, 2] float64 metres per second in the current ego frame, one row per current
        component (zeros where unmatched or parked).
    """
    if lag_s <= 0:
        raise ValueError(f"lag_s: expected > 0, got {lag_s}")
    x, y, yaw = (float(v) for v in np.asarray(past_pose, dtype=np.float64))
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    past_c = [rot @ c + (x, y) for _, _, c in past]
    pairs = []
    for i, (cls, _, c) in enumerate(current):
        gate = MAX_SPEED_MPS[cls] * lag_s
        for j, (pcls, _, _) in enumerate(past):
            d = float(np.linalg.norm(c - past_c[j]))
            if pcls == cls and d <= gate:
                pairs.append((d, i, j))
    vel = np.zeros((len(current), 2))
    used_i, used_j = set(), set()
    for d, i, j in sorted(pairs):
        if i in used_i or j in used_j:
            continue
        used_i.add(i)
        used_j.add(j)
        if d >= min_shift_voxels * grid.voxel_size[0]:
            vel[i] = (current[i][2] - past_c[j]) / lag_s
    return vel


def _shift(a: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``a`` [X, Y, ...] moved by (dx, dy) cells; what leaves the array is dropped (zeros in)."""
    out = np.zeros_like(a)
    nx, ny = a.shape[:2]
    if abs(dx) >= nx or abs(dy) >= ny:
        return out
    src = a[max(0, -dx) : nx - max(0, dx), max(0, -dy) : ny - max(0, dy)]
    out[max(0, dx) : nx - max(0, -dx), max(0, dy) : ny - max(0, -dy)] = src
    return out


def paste_shifted(frame: np.ndarray, comps: list, shifts: np.ndarray, steps: int) -> np.ndarray:
    """[S, X, Y, Z]: ``frame`` without movers, component i pasted shifted by ``shifts[i, k]``.

    Args:
        frame: [X, Y, Z] integer labels.
        comps: (class id, cells [X, Y] bool, ...) per component (:func:`bev_components`).
        shifts: [N, S, 2] int, whole cells along x and y per component and step.
        steps: S.
    """
    static = np.where(np.isin(frame, MOVABLE_CLASS_IDS), FREE_ID, frame).astype(frame.dtype)
    out = np.repeat(static[None], steps, axis=0)
    for (cls, cells, *_), shift in zip(comps, shifts):
        body = (frame == cls) & cells[..., None]  # [X, Y, Z] the component's voxels
        for k, (dx, dy) in enumerate(shift):
            out[k][_shift(body, int(dx), int(dy))] = cls
    return out


def _moved_frames(frame: np.ndarray, comps: list, vel: np.ndarray, steps: int, dt: float,
                  grid: GridSpec) -> np.ndarray:  # fmt: skip
    """[S, X, Y, Z]: ``frame`` without movers, each component pasted at ``c + v k dt``."""
    sx, sy = grid.voxel_size[0], grid.voxel_size[1]
    shifts = np.array(
        [[(int(round(v[0] * k * dt / sx)), int(round(v[1] * k * dt / sy)))
          for k in range(1, steps + 1)] for v in vel], dtype=np.int64,
    ).reshape(len(comps), steps, 2)  # fmt: skip
    return paste_shifted(frame, comps, shifts, steps)


def _check_history(history_occupancy, history_poses, grid: GridSpec, lag: int):
    """Batched torch views of a history and its poses (shapes checked; see the callers)."""
    occ, was_np = _as_torch(history_occupancy, "history_occupancy")
    poses, _ = _as_torch(history_poses, "history_poses")
    if occ.dim() not in (4, 5) or tuple(occ.shape[-3:]) != tuple(grid.shape):
        raise ValueError(
            f"history_occupancy: expected [(B,) T, {', '.join(map(str, grid.shape))}], got "
            f"{tuple(occ.shape)}"
        )
    batched = occ.dim() == 5
    occ_b = occ if batched else occ[None]
    p_b = poses if batched else poses[None]
    b, t = occ_b.shape[:2]
    if tuple(p_b.shape) != (b, t, 3):
        raise ValueError(f"history_poses: expected [(B,) {t}, 3], got {tuple(poses.shape)}")
    if not isinstance(lag, int) or not 1 <= lag < t:
        raise ValueError(f"lag: expected an int in [1, {t - 1}], got {lag!r}")
    return occ_b, p_b, batched, was_np


def object_cv_frames(
    history_occupancy,
    history_poses,
    steps: int = FUTURE_FRAMES,
    grid: GridSpec = OCC3D_GRID,
    lag: int = 2,
    dt: float = KEYFRAME_DT,
    min_shift_voxels: float = 1.0,
) -> torch.Tensor:
    """The current frame with its movers moved at their own velocities, still in the current
    ego frame (history only; matching rule in the module docstring).

    Frame k (1..S): each movable component of the current frame moved by its velocity times
    ``k * dt`` (whole voxels; what moves off the grid is gone), the rest of the frame unchanged
    and the movers' old voxels free. Warping frame k into future ego frame k
    (:func:`~renderworld.world.baselines.warp_along_poses`) gives a forecast.

    Args:
        history_occupancy: [B, T, X, Y, Z] integer labels of frames t-T+1..t (the last is the
            current frame), each in its own ego frame, on ``grid`` (torch or numpy).
        history_poses: [B, T, 3] (x, y, yaw) of those frames in the current ego frame.
        steps: S future frames.
        grid: the occupancy grid.
        lag: velocities are measured against frame ``t - lag`` (1 <= lag < T).
        dt: seconds between frames.
        min_shift_voxels: see :func:`object_velocities`.

    Returns:
        [B, S, X, Y, Z] torch tensor, the dtype and device of ``history_occupancy``.
    """
    occ_b, p_b, batched, _ = _check_history(history_occupancy, history_poses, grid, lag)
    if not batched:
        raise ValueError(
            f"history_occupancy: expected [B, T, X, Y, Z], got {tuple(occ_b.shape[1:])}"
        )
    t = occ_b.shape[1]
    frames = occ_b.detach().cpu().numpy()
    past_poses = p_b.detach().cpu().double().numpy()[:, t - 1 - lag]
    outs = []
    for i in range(occ_b.shape[0]):
        comps = bev_components(frames[i, t - 1], grid)
        past = bev_components(frames[i, t - 1 - lag], grid)
        vel = object_velocities(comps, past, past_poses[i], lag * dt, grid, min_shift_voxels)
        outs.append(torch.from_numpy(_moved_frames(frames[i, t - 1], comps, vel, steps, dt, grid)))
    return torch.stack(outs).to(occ_b.device)


def warp_frames_along_poses(frames: torch.Tensor, poses: torch.Tensor, grid: GridSpec):
    """Frame k of ``frames`` [B, S, X, Y, Z] (current ego frame) warped into the ego frame of
    pose k of ``poses`` [B, S, 3]: [B, S, X, Y, Z] (:func:`warp_along_poses`, frame by frame)."""
    b, s = frames.shape[:2]
    one = poses.reshape(b * s, 1, 3).to(frames.device)
    return warp_along_poses(frames.flatten(0, 1), one, grid)[:, 0].view(frames.shape)


def object_constant_velocity_forecast(
    history_occupancy,
    history_poses,
    steps: int = FUTURE_FRAMES,
    grid: GridSpec = OCC3D_GRID,
    lag: int = 2,
    dt: float = KEYFRAME_DT,
    min_shift_voxels: float = 1.0,
):
    """The object constant-velocity warp (history only; matching rule in the module docstring).

    Future frame k (1..S): :func:`object_cv_frames`' frame k warped into the constant-turn-rate
    pose k (:func:`~renderworld.world.baselines.warp_along_poses`).

    Args:
        history_occupancy: [T, X, Y, Z] or [B, T, X, Y, Z] integer labels of frames
            t-T+1..t (the last is the current frame), each in its own ego frame, on ``grid``.
        history_poses: [T, 3] or [B, T, 3] (x, y, yaw) of those frames in the current ego
            frame (the last row zeros).
        steps: S future frames.
        grid: the occupancy grid.
        lag: velocities are measured against frame ``t - lag`` (1 <= lag < T).
        dt: seconds between frames.
        min_shift_voxels: see :func:`object_velocities`.

    Returns:
        [S, X, Y, Z] or [B, S, X, Y, Z], the dtype and device of ``history_occupancy``.
    """
    occ_b, p_b, batched, was_np = _check_history(history_occupancy, history_poses, grid, lag)
    ctr = constant_turn_rate_poses(p_b.double(), steps)  # [B, S, 3]
    moved = object_cv_frames(occ_b, p_b, steps, grid, lag, dt, min_shift_voxels)
    out = warp_frames_along_poses(moved, ctr, grid)
    out = out if batched else out[0]
    return out.numpy() if was_np else out


def gt_movers_reference(current, future_occupancy, future_poses, grid: GridSpec = OCC3D_GRID):
    """GT-pose warp + GT movers (reads the future: a reference, never a competitor).

    Args:
        current: [X, Y, Z] or [B, X, Y, Z] integer labels of the current frame.
        future_occupancy: [S, X, Y, Z] or [B, S, X, Y, Z] ground-truth labels of frames
            t+1..t+S, each in its own ego frame.
        future_poses: [S, 3] or [B, S, 3] ground-truth (x, y, yaw) of those frames in the
            current ego frame.
        grid: the occupancy grid.

    Returns:
        [S, X, Y, Z] or [B, S, X, Y, Z] (dtype of ``current``): the current frame without its
        movers warped along ``future_poses``, and the future's movable voxels pasted over it.
    """
    cur, was_np = _as_torch(current, "current")
    fut, _ = _as_torch(future_occupancy, "future_occupancy")
    poses, _ = _as_torch(future_poses, "future_poses")
    if tuple(fut.shape[:-4]) != tuple(cur.shape[:-3]) or fut.shape[-3:] != cur.shape[-3:]:
        raise ValueError(
            f"future_occupancy: expected [(B,) S, {', '.join(map(str, cur.shape[-3:]))}] "
            f"matching current {tuple(cur.shape)}, got {tuple(fut.shape)}"
        )
    warped = warp_along_poses(remove_movers(cur), poses.double().to(cur.device), grid)
    fut = fut.to(device=cur.device, dtype=cur.dtype)
    out = torch.where(movable_mask(fut), fut, warped)
    return out.numpy() if was_np else out


def gt_pose_movers_reference(
    history_occupancy,
    history_poses,
    future_poses,
    grid: GridSpec = OCC3D_GRID,
    movers_frames: MoversFrames = object_cv_frames,
):
    """GT-pose + movers (reads the future poses: a reference, never a competitor).

    The current frame with its movers moved by ``movers_frames`` (history only), frame k warped
    into the ground-truth future ego frame k (:func:`warp_frames_along_poses`): what a pose-warp
    forecast that moves its movers by that rule would give with perfect ego poses. The default
    rule gives "GT-pose + object-CV movers"; a learned movers model's frames, the same row for
    that model.

    Args:
        history_occupancy: [T, X, Y, Z] or [B, T, X, Y, Z] integer labels of frames t-T+1..t
            (the last is the current frame), each in its own ego frame, on ``grid``.
        history_poses: [T, 3] or [B, T, 3] (x, y, yaw) of those frames in the current ego frame.
        future_poses: [S, 3] or [B, S, 3] ground-truth (x, y, yaw) of frames t+1..t+S in the
            current ego frame (metres, radians).
        grid: the occupancy grid.
        movers_frames: see :data:`MoversFrames`.

    Returns:
        [S, X, Y, Z] or [B, S, X, Y, Z], the dtype and device (numpy or torch) of
        ``history_occupancy``.
    """
    occ, was_np = _as_torch(history_occupancy, "history_occupancy")
    hist_poses, _ = _as_torch(history_poses, "history_poses")
    poses, _ = _as_torch(future_poses, "future_poses")
    batched = occ.dim() == 5
    occ_b = occ if batched else occ[None]
    hp_b = hist_poses if batched else hist_poses[None]
    p_b = poses if batched else poses[None]
    if p_b.dim() != 3 or p_b.shape[0] != occ_b.shape[0] or p_b.shape[-1] != 3:
        raise ValueError(
            f"future_poses: expected [(B,) S, 3] matching history_occupancy "
            f"{tuple(occ.shape)}, got {tuple(poses.shape)}"
        )
    frames = movers_frames(occ_b, hp_b.double(), p_b.shape[1], grid)
    out = warp_frames_along_poses(frames, p_b.double(), grid)
    out = out if batched else out[0]
    return out.numpy() if was_np else out
