"""What a plan is checked against: the forecast scene in the current ego frame.

The pose-warp world model forecasts the current frame carried along its future poses, with the
movers moved (:mod:`renderworld.world.forecast`). Expressed in the **current** ego frame, where
candidate plans live, that forecast is the current frame's static scenery standing still and
each mover moving along its forecast displacement. :class:`ForecastScene` holds it in the form
a swept ego box is tested against:

* ``points`` [P, 2]: the bird's-eye-view cell centres of everything the ego box must not touch
  (metres): object classes 0..10 and manmade / vegetation up to :data:`OBSTACLE_TOP_M` above the
  ground (a tree crown over the road is not in the way), each with the index of the mover it
  belongs to (-1: static scenery);
* ``displacements`` [M, S + 1, 2]: each mover's forecast displacement at 0, dt, ..., S dt
  (metres); later times go on at the last step's velocity;
* ``drivable`` [X, Y]: cells where some level holds driveable surface, or a road user stands
  (the road under a car is hidden by it).

The token network's fill of newly revealed space (beyond the current grid) is not part of it:
candidates are checked where the current frame saw.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from renderworld.constants import (
    KEYFRAME_DT,
    MOVABLE_CLASS_IDS,
    OCC3D_CLASSES,
    VULNERABLE_CLASS_IDS,
    GridSpec,
)
from renderworld.world.tracks import MoverTrack, track_movers

__all__ = [
    "OBSTACLE_CLASS_IDS",
    "OBSTACLE_TOP_M",
    "VULNERABLE_CLASS_IDS",
    "ForecastScene",
    "MoverForecaster",
    "constant_velocity_displacements",
    "forecast_scene",
    "head_forecaster",
    "model_forecaster",
]

#: Classes the ego box must not touch: objects (0..10), manmade, vegetation.
OBSTACLE_CLASS_IDS: tuple[int, ...] = (*range(11), OCC3D_CLASSES.index("manmade"),
                                       OCC3D_CLASSES.index("vegetation"))  # fmt: skip
#: Levels whose bottom lies below this height (metres, ego frame z) can hold an obstacle.
OBSTACLE_TOP_M = 2.0
_DRIVEABLE = OCC3D_CLASSES.index("driveable_surface")

#: ``(tracks, current [X, Y, Z], history_poses [H, 3], grid, steps, dt) -> [M, steps + 1, 2]``
#: forecast displacements (metres, 0 at the first sample) of the tracked movers.
MoverForecaster = Callable[
    [Sequence[MoverTrack], np.ndarray, np.ndarray, GridSpec, int, float], np.ndarray
]


def constant_velocity_displacements(
    tracks: Sequence[MoverTrack],
    current: np.ndarray,
    history_poses: np.ndarray,
    grid: GridSpec,
    steps: int,
    dt: float = KEYFRAME_DT,
) -> np.ndarray:
    """[M, steps + 1, 2] displacements of movers going on at their fitted velocity (metres)."""
    t = np.arange(steps + 1) * dt
    if not tracks:
        return np.zeros((0, steps + 1, 2))
    vel = np.stack([tr.velocity for tr in tracks])
    return t[None, :, None] * vel[:, None, :]


def head_forecaster(head) -> MoverForecaster:
    """The :data:`MoverForecaster` of a learned mover head
    (:func:`renderworld.world.learned_movers.head_displacements`)."""
    from renderworld.world.learned_movers import head_displacements

    def movers(tracks, current, history_poses, grid, steps, dt=KEYFRAME_DT) -> np.ndarray:
        disp = head_displacements(head, current, history_poses, tracks, grid, steps, dt)
        return np.concatenate([np.zeros((len(disp), 1, 2)), disp], axis=1)

    return movers


def model_forecaster(world_model) -> MoverForecaster:
    """The mover forecast a checked plan reads for ``world_model``: its mover head when its
    forecast moves others by it (``movers="learned"``), else each tracked mover at its fitted
    velocity."""
    head = getattr(world_model, "mover_head", None)
    if head is not None and getattr(world_model, "movers", None) == "learned":
        return head_forecaster(head)
    return constant_velocity_displacements


@dataclass
class ForecastScene:
    """The forecast in the current ego frame (module docstring).

    Attributes:
        points: [P, 2] metres, obstacle cell centres at t = 0.
        mover: [P] int, the mover each point belongs to (-1: static scenery).
        agent: [P] bool, points of a road user (a movable class), moving or not.
        vulnerable: [P] bool, points of a pedestrian, cyclist or motorcyclist.
        displacements: [M, S + 1, 2] metres, each mover's displacement at 0, dt, ... S dt.
        dt: seconds between displacement samples.
        drivable: [X, Y] bool.
        grid: the occupancy grid.
        tracks: the movers (:class:`~renderworld.world.tracks.MoverTrack`).
    """

    points: np.ndarray
    mover: np.ndarray
    agent: np.ndarray
    vulnerable: np.ndarray
    displacements: np.ndarray
    dt: float
    drivable: np.ndarray
    grid: GridSpec
    tracks: list = field(default_factory=list)

    def mover_displacement(self, times: np.ndarray) -> np.ndarray:
        """[M, T, 2] metres: each mover's displacement at ``times`` [T] seconds (>= 0); beyond
        the last sample it goes on at the last step's velocity."""
        disp = self.displacements
        m, n = disp.shape[:2]
        times = np.asarray(times, dtype=np.float64)
        if m == 0:
            return np.zeros((0, len(times), 2))
        grid_t = np.arange(n) * self.dt
        u = np.clip(times / self.dt, 0.0, n - 1)
        k = np.minimum(np.floor(u).astype(int), n - 2) if n > 1 else np.zeros(len(u), int)
        if n == 1:
            return np.repeat(disp[:, :1], len(times), axis=1)
        w = (u - k)[None, :, None]
        out = disp[:, k] * (1 - w) + disp[:, k + 1] * w
        late = times > grid_t[-1]
        if late.any():
            vel = (disp[:, -1] - disp[:, -2]) / self.dt
            out[:, late] = disp[:, -1:] + vel[:, None] * (times[late] - grid_t[-1])[None, :, None]
        return out

    def points_at(self, times: np.ndarray) -> np.ndarray:
        """[T, P, 2]: every obstacle point at ``times`` [T] seconds (static ones stand still)."""
        times = np.asarray(times, dtype=np.float64)
        out = np.repeat(self.points[None], len(times), axis=0)
        moving = self.mover >= 0
        if moving.any():
            disp = self.mover_displacement(times)  # [M, T, 2]
            out[:, moving] += disp[self.mover[moving]].transpose(1, 0, 2)
        return out

    def on_drivable(self, xy: np.ndarray) -> np.ndarray:
        """[...] bool: positions [..., 2] (metres) on a drivable cell; off the grid counts as
        drivable (nothing is known there)."""
        g = self.grid
        ix = np.floor((xy[..., 0] - g.range_min[0]) / g.voxel_size[0]).astype(int)
        iy = np.floor((xy[..., 1] - g.range_min[1]) / g.voxel_size[1]).astype(int)
        inside = (ix >= 0) & (ix < g.shape[0]) & (iy >= 0) & (iy < g.shape[1])
        out = np.ones(xy.shape[:-1], dtype=bool)
        out[inside] = self.drivable[ix[inside], iy[inside]]
        return out


def forecast_scene(
    history_occupancy: np.ndarray,
    history_poses: np.ndarray,
    grid: GridSpec,
    steps: int,
    dt: float = KEYFRAME_DT,
    movers: MoverForecaster = constant_velocity_displacements,
    min_shift_voxels: float = 1.0,
) -> ForecastScene:
    """The :class:`ForecastScene` of a history.

    Args:
        history_occupancy: [T, X, Y, Z] integer Occ3D labels of frames t-T+1..t, each in its
            own ego frame, on ``grid``.
        history_poses: [T, 3] (x, y, yaw) of those frames in the current ego frame.
        grid: the occupancy grid.
        steps: S forecast steps.
        dt: seconds per step.
        movers: forecasts the tracked movers' displacements (default: constant velocity; a
            learned mover head: :func:`head_forecaster`).
        min_shift_voxels: :func:`~renderworld.world.tracks.track_movers`' moving threshold.

    Raises:
        ValueError: naming the argument on a shape mismatch.
    """
    occ = np.asarray(history_occupancy)
    tracks = track_movers(occ, history_poses, grid, dt, min_shift_voxels)
    current = occ[-1]
    z_bottom = grid.range_min[2] + np.arange(grid.shape[2]) * grid.voxel_size[2]
    low = current[..., z_bottom < OBSTACLE_TOP_M]
    obstacle = np.isin(low, OBSTACLE_CLASS_IDS).any(-1)  # [X, Y]
    movable = np.isin(current, MOVABLE_CLASS_IDS).any(-1)
    drivable = (current == _DRIVEABLE).any(-1) | movable
    mover_of = np.full(grid.shape[:2], -1, dtype=np.int64)
    for i, tr in enumerate(tracks):
        mover_of[tr.cells] = i
    ix, iy = np.nonzero(obstacle | (mover_of >= 0))
    pts = np.stack([grid.range_min[0] + (ix + 0.5) * grid.voxel_size[0],
                    grid.range_min[1] + (iy + 0.5) * grid.voxel_size[1]], -1)  # fmt: skip
    disp = movers(tracks, current, np.asarray(history_poses, dtype=np.float64), grid, steps, dt)
    disp = np.asarray(disp, dtype=np.float64).reshape(len(tracks), steps + 1, 2)
    return ForecastScene(
        points=pts.astype(np.float64),
        mover=mover_of[ix, iy],
        agent=movable[ix, iy],
        vulnerable=np.isin(current, VULNERABLE_CLASS_IDS).any(-1)[ix, iy],
        displacements=disp,
        dt=float(dt),
        drivable=drivable,
        grid=grid,
        tracks=list(tracks),
    )
