"""Ego-box collision tests on a BEV raster (docs/protocol.md#collision-rate).

* The ego box is ``EGO_LENGTH`` x ``EGO_WIDTH`` (4.084 m x 1.85 m) **centred at the waypoint**
  (the waypoint is the ego-frame origin, i.e. the rear axle in nuScenes; centring the box there
  follows ST-P3/UniAD's evaluation, which places the box centre at the planned point - it
  shifts the body ~1.5 m backwards relative to reality, the same for every method).
* Heading at waypoint k = direction of travel from waypoint k-1 to k (waypoint 0 = origin).
  When a step is shorter than ``MIN_STEP_FOR_HEADING`` (standing still) the previous heading is
  kept; the heading before the first step is the current heading, 0 (ego x axis).
* Rasterisation: a box covers the BEV cells whose **centres** lie inside it, plus every cell
  crossed by one of its two centre lines (the length-wise and the width-wise segment through
  its centre), so a thin box (a 0.4 m wide bicycle) or one smaller than a cell is never
  dropped between cell centres.
* Agents: boxes ``[M, 5]`` = (x, y, length, width, yaw) or ``[M, 7]`` =
  (x, y, z, length, width, height, yaw), metres/radians, current ego frame; length along the
  box's heading. Rasterised on a 0.5 m grid over [-50, 50] m (ST-P3's 200 x 200 BEV).
* Occupancy: voxels of ``OBJECT_CLASS_IDS`` (1..10) at any height, projected to BEV on the
  occupancy's own grid; each future occupancy frame may be in its own ego frame, given that
  frame's pose in the current ego frame.
* A waypoint whose ego box covers no cell of the grid cannot be judged: it is reported as not
  evaluable (and counted by the caller), never as "no collision".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from renderworld.constants import EGO_LENGTH, EGO_WIDTH, OBJECT_CLASS_IDS, GridSpec

__all__ = [
    "COLLISION_BEV_GRID",
    "MIN_STEP_FOR_HEADING",
    "BevGrid",
    "box_cells",
    "collisions_with_boxes",
    "collisions_with_occupancy",
    "rasterize_boxes",
    "trajectory_headings",
]

MIN_STEP_FOR_HEADING = 0.05  # metres; shorter steps keep the previous heading


@dataclass(frozen=True)
class BevGrid:
    """A 2D raster in the current ego frame: cell (i, j) covers
    [x_min + i*res, x_min + (i+1)*res) x [y_min + j*res, ...)."""

    x_min: float
    y_min: float
    resolution: float
    nx: int
    ny: int

    @classmethod
    def from_grid_spec(cls, spec: GridSpec) -> BevGrid:
        """The x/y part of a voxel grid (square voxels required)."""
        sx, sy, _ = spec.voxel_size
        if abs(sx - sy) > 1e-9:
            raise ValueError(f"spec: expected square BEV voxels, got {sx} x {sy} m")
        return cls(spec.range_min[0], spec.range_min[1], sx, spec.shape[0], spec.shape[1])


#: ST-P3/UniAD planning BEV: 0.5 m cells over [-50, 50] m.
COLLISION_BEV_GRID = BevGrid(-50.0, -50.0, 0.5, 200, 200)


def trajectory_headings(trajectory: np.ndarray) -> np.ndarray:
    """Heading (rad, current ego frame) at each waypoint from the direction of travel.

    Args:
        trajectory: [S, 2] metres, waypoints of frames t+1..t+S in the current ego frame.

    Returns:
        [S] radians.
    """
    traj = np.asarray(trajectory, dtype=np.float64)
    prev = np.zeros(2)
    heading = 0.0
    out = np.empty(len(traj))
    for k, p in enumerate(traj):
        step = p - prev
        if math.hypot(step[0], step[1]) >= MIN_STEP_FOR_HEADING:
            heading = math.atan2(step[1], step[0])
        out[k] = heading
        prev = p
    return out


def box_cells(
    cx: float, cy: float, length: float, width: float, yaw: float, grid: BevGrid
) -> tuple[np.ndarray, np.ndarray]:
    """Cells of ``grid`` covered by a rotated box (see module docstring for the rule).

    Returns:
        (ix [N], iy [N]) int64 indices inside the grid (possibly empty, possibly repeated).
    """
    c, s = math.cos(yaw), math.sin(yaw)
    hx = 0.5 * (abs(c) * length + abs(s) * width)  # half extent of the axis-aligned hull
    hy = 0.5 * (abs(s) * length + abs(c) * width)
    r = grid.resolution
    i0 = max(int(math.floor((cx - hx - grid.x_min) / r)), 0)
    i1 = min(int(math.floor((cx + hx - grid.x_min) / r)), grid.nx - 1)
    j0 = max(int(math.floor((cy - hy - grid.y_min) / r)), 0)
    j1 = min(int(math.floor((cy + hy - grid.y_min) / r)), grid.ny - 1)
    if i0 > i1 or j0 > j1:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
    lo_x, lo_y = grid.x_min + ii * r, grid.y_min + jj * r
    dx, dy = lo_x + 0.5 * r - cx, lo_y + 0.5 * r - cy
    u = c * dx + s * dy  # cell centre along the box heading
    v = -s * dx + c * dy
    covered = (np.abs(u) <= 0.5 * length + 1e-9) & (np.abs(v) <= 0.5 * width + 1e-9)
    for half, (ex, ey) in ((0.5 * length, (c, s)), (0.5 * width, (-s, c))):
        covered |= _segment_hits_cells(
            cx - half * ex, cy - half * ey, 2 * half * ex, 2 * half * ey, lo_x, lo_y, r
        )
    return ii[covered].astype(np.int64), jj[covered].astype(np.int64)


def _segment_hits_cells(
    x0: float, y0: float, vx: float, vy: float, lo_x: np.ndarray, lo_y: np.ndarray, r: float
) -> np.ndarray:
    """Does segment (x0, y0) + t (vx, vy), t in [0, 1], meet each closed cell [lo, lo + r]?

    Slab test (Liang-Barsky) vectorised over cells; returns bool of ``lo_x``'s shape.
    """
    t_lo = np.zeros(lo_x.shape)
    t_hi = np.ones(lo_x.shape)
    ok = np.ones(lo_x.shape, dtype=bool)
    for p0, vel, lo in ((x0, vx, lo_x), (y0, vy, lo_y)):
        if abs(vel) < 1e-12:
            ok &= (p0 >= lo) & (p0 <= lo + r)
        else:
            ta, tb = (lo - p0) / vel, (lo + r - p0) / vel
            t_lo = np.maximum(t_lo, np.minimum(ta, tb))
            t_hi = np.minimum(t_hi, np.maximum(ta, tb))
    return ok & (t_lo <= t_hi)


def _box_params(boxes: np.ndarray) -> np.ndarray:
    """[M, 5|7] -> [M, 5] (x, y, length, width, yaw)."""
    if boxes.shape[-1] == 5:
        return boxes
    return boxes[..., [0, 1, 3, 4, 6]]


def rasterize_boxes(boxes: np.ndarray, grid: BevGrid = COLLISION_BEV_GRID) -> np.ndarray:
    """BEV raster of boxes.

    Args:
        boxes: [M, 5] or [M, 7] (module docstring layout), metres / radians, finite.

    Returns:
        [nx, ny] bool.
    """
    out = np.zeros((grid.nx, grid.ny), dtype=bool)
    for x, y, length, width, yaw in _box_params(np.asarray(boxes, dtype=np.float64)):
        ix, iy = box_cells(x, y, length, width, yaw, grid)
        out[ix, iy] = True
    return out


def _check_trajs(trajectory) -> tuple[np.ndarray, bool]:
    """[S, 2] or [N, S, 2] -> ([N, S, 2] float64, was_single)."""
    traj = np.asarray(trajectory, dtype=np.float64)
    single = traj.ndim == 2
    traj = traj[None] if single else traj
    if traj.ndim != 3 or traj.shape[2] != 2 or not np.isfinite(traj).all():
        raise ValueError(
            f"trajectory: expected finite [S, 2] or [N, S, 2] metres, got shape "
            f"{np.shape(trajectory)}"
        )
    return traj, single


def _ego_hits(trajs: np.ndarray, hazard: np.ndarray, grid: BevGrid, poses=None):
    """Ego boxes of [N, S, 2] waypoints against hazard rasters [S, nx, ny].

    ``poses`` [S, 3] (x, y, yaw of raster k's frame in the current frame) or None.
    Returns (collides [N, S], evaluable [N, S]).
    """
    n, s, _ = trajs.shape
    collides = np.zeros((n, s), dtype=bool)
    evaluable = np.zeros((n, s), dtype=bool)
    for j in range(n):
        headings = trajectory_headings(trajs[j])
        for k in range(s):
            (x, y), yaw = trajs[j, k], headings[k]
            if poses is not None:  # express the ego box in frame k's own ego frame
                px, py, pyaw = poses[k]
                c, sn = math.cos(pyaw), math.sin(pyaw)
                x, y = c * (x - px) + sn * (y - py), -sn * (x - px) + c * (y - py)
                yaw = yaw - pyaw
            ix, iy = box_cells(x, y, EGO_LENGTH, EGO_WIDTH, yaw, grid)
            evaluable[j, k] = ix.size > 0
            collides[j, k] = evaluable[j, k] and bool(hazard[k][ix, iy].any())
    return collides, evaluable


def collisions_with_boxes(
    trajectory, boxes, box_valid=None, grid: BevGrid = COLLISION_BEV_GRID
) -> tuple[np.ndarray, np.ndarray]:
    """Does the ego box at each waypoint overlap an agent box of the same future step?

    Args:
        trajectory: [S, 2] metres, current ego frame, or [N, S, 2] for N trajectories checked
            against the same boxes (rasterised once).
        boxes: [S, M, 5] or [S, M, 7] agent boxes at each future step, current ego frame.
        box_valid: [S, M] bool (False = padding row) or None (all valid; then no NaN allowed).
        grid: the BEV raster.

    Returns:
        (collides, evaluable), bool [S] (or [N, S]); ``evaluable`` is False where the ego box
        covers no grid cell.
    """
    trajs, single = _check_trajs(trajectory)
    b = np.asarray(boxes, dtype=np.float64)
    s = trajs.shape[1]
    if b.ndim != 3 or b.shape[0] != s or b.shape[2] not in (5, 7):
        raise ValueError(f"boxes: expected [S={s}, M, 5 or 7], got {b.shape}")
    if box_valid is None:
        valid = np.ones(b.shape[:2], dtype=bool)
    else:
        valid = np.asarray(box_valid)
        if valid.shape != b.shape[:2] or valid.dtype != np.bool_:
            raise ValueError(
                f"box_valid: expected bool {b.shape[:2]}, got {valid.dtype} {valid.shape}"
            )
    if not np.isfinite(b[valid]).all():
        raise ValueError(
            "boxes: expected finite values in valid rows (mark padding with box_valid)"
        )
    hazard = np.stack([rasterize_boxes(b[k][valid[k]], grid) for k in range(s)])
    collides, evaluable = _ego_hits(trajs, hazard, grid)
    return (collides[0], evaluable[0]) if single else (collides, evaluable)


def collisions_with_occupancy(
    trajectory, occupancy, grid: GridSpec, frame_poses=None
) -> tuple[np.ndarray, np.ndarray]:
    """Does the ego box at each waypoint cover an object voxel (classes 1..10) in BEV?

    Args:
        trajectory: [S, 2] metres, current ego frame, or [N, S, 2].
        occupancy: [S, X, Y, Z] integer labels of the future frames t+1..t+S on ``grid``.
        grid: the occupancy's voxel grid (square BEV voxels).
        frame_poses: [S, 3] (x, y, yaw) of each occupancy frame's ego origin in the current ego
            frame, or None when the occupancy is already expressed in the current ego frame.

    Returns:
        (collides, evaluable), bool [S] (or [N, S]).
    """
    trajs, single = _check_trajs(trajectory)
    occ = np.asarray(occupancy)
    s = trajs.shape[1]
    if occ.ndim != 4 or occ.shape[0] != s or tuple(occ.shape[1:]) != tuple(grid.shape):
        raise ValueError(
            f"occupancy: expected [S={s}, {', '.join(map(str, grid.shape))}], got {occ.shape}"
        )
    poses = None
    if frame_poses is not None:
        poses = np.asarray(frame_poses, dtype=np.float64)
        if poses.shape != (s, 3) or not np.isfinite(poses).all():
            raise ValueError(f"frame_poses: expected finite [S={s}, 3], got {poses.shape}")
    if not np.issubdtype(occ.dtype, np.integer) or (
        occ.size and (occ.min() < 0 or occ.max() > 255)
    ):
        raise ValueError(f"occupancy: expected integer class ids in [0, 255], got {occ.dtype}")
    is_object = np.zeros(256, dtype=bool)
    is_object[list(OBJECT_CLASS_IDS)] = True
    objects = is_object[occ].any(axis=-1)  # [S, X, Y]
    collides, evaluable = _ego_hits(trajs, objects, BevGrid.from_grid_spec(grid), poses)
    return (collides[0], evaluable[0]) if single else (collides, evaluable)
