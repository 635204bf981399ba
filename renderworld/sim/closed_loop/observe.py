"""What a closed-loop planner sees: occupancy at the ego's actual pose, history poses, command.

* Occupancy: Occ3D semantics of the world rendered at the ego's **actual** pose, on the
  planner's grid, and nothing else (no masks, images or LiDAR). When the planner's grid is an
  integer down-sampling of the Occ3D grid (every named grid), the world is voxelised at the
  Occ3D grid and down-sampled by the datasets' rule
  (:func:`renderworld.data.downsample.downsample_occupancy`), so a planner sees frames made
  exactly as its training data were; any other grid is voxelised directly.
* History: the ego's actual poses at the last keyframes, expressed in the current ego frame as
  the planner API expects (displacements between consecutive frames and each frame's yaw).
* Command: where the logged ego goes next, as a navigation system would say it. The logged
  pose closest to the actual ego position is found (first closest sample over the scene); the
  logged positions 0.5 ... 3.0 s after it, expressed in the **actual** ego frame, give the
  command by the datasets' rule (:func:`renderworld.world.ego.command_from_trajectory`: lateral
  offset at 3 s beyond +-2 m; past the scene end, the last logged point before it).
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import FUTURE_FRAMES, KEYFRAME_DT, OCC3D_GRID, GridSpec
from renderworld.data.downsample import downsample_occupancy, grid_factor
from renderworld.sim.layout import World
from renderworld.sim.occupancy import SemanticVoxeliser
from renderworld.world.ego import command_from_trajectory

__all__ = ["OccupancyRenderer", "pose_matrix_2d", "history_inputs", "route_command"]


def pose_matrix_2d(x: float, y: float, yaw: float) -> np.ndarray:
    """[4, 4] ego (rear axle) -> scene frame of a ground pose; z = 0."""
    m = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:2, 3] = x, y
    return m


def _same_range(a: GridSpec, b: GridSpec) -> bool:
    return np.allclose(a.range_min, b.range_min) and np.allclose(a.range_max, b.range_max)


class OccupancyRenderer:
    """Occ3D semantics [X, Y, Z] uint8 of a world at any ego pose, on one grid.

    Args:
        grid: the planner's grid.
    """

    def __init__(self, grid: GridSpec):
        if not isinstance(grid, GridSpec):
            raise TypeError(f"grid: expected a GridSpec, got {type(grid).__name__}")
        self.grid = grid
        self.factor = None
        fine = grid
        if _same_range(grid, OCC3D_GRID):
            try:
                self.factor = grid_factor(OCC3D_GRID.shape, grid)
                fine = OCC3D_GRID
            except ValueError:
                self.factor = None
        self._vox = SemanticVoxeliser(fine)

    def render(self, world: World, t: float, pose: np.ndarray) -> np.ndarray:
        """Semantics at time ``t`` (s) seen from ``pose`` ([4, 4] ego -> scene)."""
        sem = self._vox.semantics(world, t, pose)
        if self.factor is not None and self.factor != (1, 1, 1):
            sem = downsample_occupancy(sem, self.factor)
        return sem


def history_inputs(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planner history from ego poses (x, y, yaw) [H, 3], scene frame, oldest first.

    Returns:
        (displacements [H-1, 2] float64 metres, yaws [H] float64 radians), both in the
        current (last) ego frame, as :class:`renderworld.planning.PlanRequest` takes them.
    """
    p = np.asarray(poses, dtype=np.float64)
    x0, y0, yaw0 = p[-1]
    c, s = np.cos(yaw0), np.sin(yaw0)
    dx, dy = p[:, 0] - x0, p[:, 1] - y0
    local = np.stack([c * dx + s * dy, -s * dx + c * dy], -1)
    yaws = (p[:, 2] - yaw0 + np.pi) % (2 * np.pi) - np.pi
    yaws[-1] = 0.0
    return np.diff(local, axis=0), yaws


def route_command(world: World, x: float, y: float, yaw: float) -> str:
    """The navigation command at the actual ego pose (module docstring: how)."""
    traj = world.ego.trajectory
    keep = (traj.times >= 0.0) & (traj.times <= world.duration)
    times, xy = traj.times[keep], traj.xy[keep]
    i = int(np.argmin(np.hypot(xy[:, 0] - x, xy[:, 1] - y)))
    t_fut = times[i] + KEYFRAME_DT * np.arange(1, FUTURE_FRAMES + 1)
    fut, _ = traj.pose(t_fut)
    c, s = np.cos(yaw), np.sin(yaw)
    d = fut - np.array([x, y])
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
    return command_from_trajectory(local, t_fut <= world.duration + 1e-9)
