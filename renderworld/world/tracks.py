"""Other road users tracked through the occupancy history: where each one was, how it moves.

A mover is a movable bird's-eye-view component of the current frame
(:func:`renderworld.world.movers.bev_components`: one movable class, 8-connected cells). Its
track follows it back through every history frame, each brought into the current ego frame by
its pose, so the ego's own motion is compensated:

* **Merged movers split** (oldest frame first): at coarse voxels two cars side by side (a lead
  car and an oncoming one in the next lane) touch and form one component, which would then
  follow one car's history and carry both cells with it. Where one component covers the
  footprints of two or more movers of the frame before (each carried on by its velocity from
  the two frames before) whose velocities differ by at least :data:`SPLIT_SPEED_MPS`, its
  cells go to the nearest footprint.
* **Matching** (newest frame first): a track's next older position is predicted from its
  velocity so far (none yet: where it was last seen, and each older component is first carried
  on to now by its own velocity from the frame before it, so that of two movers passing side
  by side the one that comes here continues the track); the nearest component of the same class
  within the gate ``GATE_M + max_speed * gap`` of that prediction (``gap`` seconds since the
  track was last seen; the class's :data:`~renderworld.world.movers.MAX_SPEED_MPS` while the
  track has no velocity, :data:`GATE_SPEED_MPS` once it has) continues it, closest pairs
  first, one to one. A frame where no component fits is skipped (occlusion), not the end.
* **Velocity**: the least-squares slope of the matched centroids over their times (every
  frame, not only two: the centroid of a component jitters by up to half a voxel from frame to
  frame as the grid moves with the ego, and a fit over 2 s averages that out).
* **Moving or not**: a track moves when its fitted displacement over its time span is at least
  ``min_shift_voxels`` voxels; otherwise its velocity is zero (a parked car stays where it
  is). A pedestrian at 1.1 m/s crosses 2.2 m in the 2 s history, more than one 1.6 m voxel of
  the coarse grid, so it moves; a shift measured over one second (lag 2) would have frozen it.

Frames: the current ego frame (x forward, y left; metres, seconds). Inputs are numpy arrays.

A plan tracks one history several times (the world model's stop rule, its mover forecast, the
forecast check): :func:`track_movers` keeps the tracks of the last :data:`CACHE_SIZE` histories,
keyed by their content, and gives the same (read-only) tracks back for the same history.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from renderworld.constants import KEYFRAME_DT, GridSpec
from renderworld.world.movers import MAX_SPEED_MPS, bev_components

__all__ = [
    "GATE_M",
    "GATE_SPEED_MPS",
    "SPLIT_SPEED_MPS",
    "CACHE_SIZE",
    "MoverTrack",
    "cell_xy",
    "clear_track_cache",
    "fit_velocity",
    "track_movers",
]

#: Slack of the matching gate, metres (a centroid's quantisation at coarse voxels).
GATE_M = 1.0
#: Speed change a track may show between frames once its velocity is known, m/s.
GATE_SPEED_MPS = 4.0
#: Two movers of a frame that one component of the next frame covers are split apart again when
#: their velocities differ by at least this much, m/s (a car passing one in the next lane).
SPLIT_SPEED_MPS = 3.0


@dataclass
class MoverTrack:
    """One mover of the current frame and its history.

    Attributes:
        cls: Occ3D class id.
        cells: [X, Y] bool, its bird's-eye-view cells in the current frame.
        centroid: [2] metres, its current centroid.
        times: [K] seconds (<= 0) of the frames it was seen in, newest first (K >= 1).
        centroids: [K, 2] metres, its centroid at those times, current ego frame.
        velocity: [2] m/s, the fitted velocity (zeros when it does not move).
        moving: whether its fitted displacement passed the threshold.
    """

    cls: int
    cells: np.ndarray
    centroid: np.ndarray
    times: np.ndarray
    centroids: np.ndarray
    velocity: np.ndarray
    moving: bool


def _to_current(comps: list, pose: np.ndarray) -> list[np.ndarray]:
    x, y, yaw = (float(v) for v in pose)
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    return [rot @ c + (x, y) for _, _, c in comps]


def cell_xy(cells: np.ndarray, grid: GridSpec) -> np.ndarray:
    """[K, 2] centres (metres, the frame's own ego frame) of the ``cells`` [X, Y] set."""
    ix, iy = np.nonzero(cells)
    return np.stack([grid.range_min[0] + (ix + 0.5) * grid.voxel_size[0],
                     grid.range_min[1] + (iy + 0.5) * grid.voxel_size[1]], 1)  # fmt: skip


def _split_frame(comps: list, pose, feet: list, vel: np.ndarray, cls: np.ndarray,
                 grid: GridSpec, split_speed: float) -> list:  # fmt: skip
    """Components of one frame, each covering two or more differently moving movers of the
    frame before split among them: each cell goes to the nearest mover's footprint ``feet``
    (cell centres [K, 2], current ego frame) carried on by its velocity ``vel`` [M, 2]."""
    x, y, yaw = (float(v) for v in pose)
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    reach = GATE_M + float(grid.voxel_size[0])
    out = []
    for c_cls, cells, c in comps:
        own = cell_xy(cells, grid)
        xy = own @ rot.T + (x, y)  # current ego frame
        d = np.stack([np.hypot(*(xy[:, None] - f[None]).transpose(2, 0, 1)).min(1)
                      for f in feet]) if feet else np.zeros((0, len(xy)))  # fmt: skip
        near = np.flatnonzero((cls == c_cls) & (d.min(1, initial=np.inf) <= reach))
        v = vel[near]
        spread = np.hypot(*(v[:, None] - v[None]).transpose(2, 0, 1)).max() if len(v) else 0.0
        if len(near) < 2 or spread < split_speed:
            out.append((c_cls, cells, c))
            continue
        owner = near[np.argmin(d[near], axis=0)]
        ix, iy = np.nonzero(cells)
        for m in np.unique(owner):
            part = np.zeros_like(cells)
            part[ix[owner == m], iy[owner == m]] = True
            out.append((c_cls, part, own[owner == m].mean(0)))
    return out


def _split_merged(frames: list, poses: np.ndarray, grid: GridSpec, dt: float,
                  split_speed: float) -> list:  # fmt: skip
    """Oldest frame first: a frame's components split where they cover movers of the frame
    before that move apart (velocities from the two frames before, nearest match)."""
    out = list(frames[:2])
    for k in range(2, len(frames)):
        prev, older = out[k - 1], out[k - 2]
        if not prev or not older:
            out.append(frames[k])
            continue
        c1 = np.stack(_to_current(prev, poses[k - 1]))
        cls1 = np.array([p[0] for p in prev])
        vel = _frame_velocities(c1, cls1, older, poses[k - 2], dt)
        ok = np.flatnonzero(~np.isnan(vel[:, 0]))
        vel = vel[ok]
        xk, yk, yawk = (float(v) for v in poses[k - 1])
        rot = np.array([[np.cos(yawk), -np.sin(yawk)], [np.sin(yawk), np.cos(yawk)]])
        feet = [cell_xy(prev[m][1], grid) @ rot.T + (xk, yk) + vel[i] * dt
                for i, m in enumerate(ok)]  # fmt: skip
        out.append(_split_frame(frames[k], poses[k], feet, vel, cls1[ok], grid, split_speed))
    return out


def _frame_velocities(c1: np.ndarray, cls1: np.ndarray, older: list, pose, dt: float):
    """[M, 2] m/s: the velocity of each mover of a frame (centroids ``c1`` [M, 2], classes
    ``cls1`` [M], current ego frame) from its nearest one of the same class in the frame
    ``dt`` before (``older``, taken at ``pose``) within the gate; NaN where none is."""
    vel = np.full((len(c1), 2), np.nan)
    if not len(older):
        return vel
    c2 = np.stack(_to_current(older, pose))
    cls2 = np.array([p[0] for p in older])
    d = np.hypot(*(c1[:, None] - c2[None]).transpose(2, 0, 1))
    d = np.where(cls1[:, None] == cls2[None], d, np.inf)
    j = d.argmin(1)
    gate = GATE_M + np.array([MAX_SPEED_MPS[c] for c in cls1]) * dt
    ok = d[np.arange(len(c1)), j] <= gate
    vel[ok] = (c1[ok] - c2[j[ok]]) / dt
    return vel


def fit_velocity(times: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Least-squares slope [2] (m/s) of positions [K, 2] over times [K] (zeros for K < 2)."""
    if len(times) < 2:
        return np.zeros(2)
    t = times - times.mean()
    return (t[:, None] * (xy - xy.mean(0))).sum(0) / float((t * t).sum())


#: Histories whose tracks :func:`track_movers` keeps.
CACHE_SIZE = 4
_CACHE: OrderedDict = OrderedDict()
_LOCK = threading.Lock()


def clear_track_cache() -> None:
    """Forget every kept track set (a benchmark that plans one history again and again clears
    it before each plan, so that each pays its first tracking, as a car's next history does)."""
    with _LOCK:
        _CACHE.clear()


def _cache_key(occ: np.ndarray, poses: np.ndarray, *args) -> tuple:
    """The history's content (labels as uint8 where they fit, whatever their dtype) and the
    other arguments."""
    if occ.dtype != np.uint8 and occ.size and occ.min() >= 0 and occ.max() <= 255:
        occ = occ.astype(np.uint8)
    h = hashlib.blake2b(digest_size=16)
    for part in (occ.dtype.str, occ.shape, np.ascontiguousarray(occ), poses):
        h.update(part.tobytes() if isinstance(part, np.ndarray) else str(part).encode())
    return (h.digest(), *args)


def _frozen(tracks: list[MoverTrack]) -> list[MoverTrack]:
    for tr in tracks:
        for a in (tr.cells, tr.centroid, tr.times, tr.centroids, tr.velocity):
            a.setflags(write=False)
    return tracks


def track_movers(
    history_occupancy: np.ndarray,
    history_poses: np.ndarray,
    grid: GridSpec,
    dt: float = KEYFRAME_DT,
    min_shift_voxels: float = 1.0,
    split_speed_mps: float | None = SPLIT_SPEED_MPS,
) -> list[MoverTrack]:
    """Track every mover of the current frame back through the history (module docstring).

    Args:
        history_occupancy: [T, X, Y, Z] integer labels of frames t-T+1..t, each in its own ego
            frame, on ``grid``.
        history_poses: [T, 3] (x, y, yaw) of those frames in the current ego frame (last zeros).
        grid: the occupancy grid.
        dt: seconds between frames.
        min_shift_voxels: a track moves when its fitted displacement over its span is at least
            this many x-voxels.
        split_speed_mps: split merged components (module docstring) apart when the movers
            they cover differ in velocity by this much (m/s); None: never.

    Returns:
        One :class:`MoverTrack` per movable component of the current frame, in
        :func:`~renderworld.world.movers.bev_components` order; its arrays are read-only (the
        same tracks are given back for the same history, module docstring).

    Raises:
        ValueError: naming the argument on a shape mismatch.
    """
    occ = np.asarray(history_occupancy)
    poses = np.asarray(history_poses, dtype=np.float64)
    if occ.ndim != 4 or tuple(occ.shape[1:]) != tuple(grid.shape):
        raise ValueError(
            f"history_occupancy: expected [T, {', '.join(map(str, grid.shape))}], got {occ.shape}"
        )
    t_n = occ.shape[0]
    if poses.shape != (t_n, 3):
        raise ValueError(f"history_poses: expected [{t_n}, 3], got {poses.shape}")
    key = _cache_key(occ, poses, grid, float(dt), float(min_shift_voxels), split_speed_mps)
    with _LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return list(_CACHE[key])
    tracks = _frozen(_track(occ, poses, grid, dt, min_shift_voxels, split_speed_mps))
    with _LOCK:
        _CACHE[key] = tracks
        while len(_CACHE) > CACHE_SIZE:
            _CACHE.popitem(last=False)
    return list(tracks)


def _track(occ, poses, grid, dt, min_shift_voxels, split_speed_mps) -> list[MoverTrack]:
    """:func:`track_movers` without the cache (its arguments checked)."""
    t_n = occ.shape[0]
    frames = [bev_components(occ[k], grid) for k in range(t_n)]
    if split_speed_mps is not None:
        frames = _split_merged(frames, poses, grid, dt, split_speed_mps)
    current = frames[-1]
    cur_cls = np.array([cls for cls, _, _ in current])
    seen_t = [[0.0] for _ in current]
    seen_c = [[c] for _, _, c in current]
    for k in range(t_n - 2, -1, -1):
        past = frames[k]
        if not past or not current:
            continue
        past_c = np.stack(_to_current(past, poses[k]))  # [M, 2]
        past_cls = np.array([pcls for pcls, _, _ in past])
        t_k = (k - (t_n - 1)) * dt
        preds, gates = np.empty((len(current), 2)), np.empty(len(current))
        fresh = np.array([len(seen_t[i]) == 1 for i in range(len(current))])
        for i, (cls, _, _) in enumerate(current):
            times, cents = np.array(seen_t[i]), np.array(seen_c[i])
            vel = fit_velocity(times, cents)
            gap = times[-1] - t_k
            preds[i] = cents[-1] - vel * gap
            speed = GATE_SPEED_MPS if len(times) > 1 else MAX_SPEED_MPS[cls]
            gates[i] = GATE_M + speed * gap
        diff = past_c[None] - preds[:, None]  # [N, M, 2]
        if fresh.any() and k > 0 and frames[k - 1]:
            # A track seen only now has no velocity: each older mover is carried on to now by
            # its own (from the frame before it), so that of two movers passing side by side
            # the one that comes here continues it, not the nearer one's old place.
            vel_k = _frame_velocities(past_c, past_cls, frames[k - 1], poses[k - 1], dt)
            carried = past_c + np.nan_to_num(vel_k) * -t_k
            diff[fresh] = carried[None] - preds[fresh][:, None]
        dist = np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)
        ok = (cur_cls[:, None] == past_cls[None]) & (dist <= gates[:, None])
        ii, jj = np.nonzero(ok)
        dd = dist[ii, jj]
        order = np.lexsort((jj, ii, dd))  # closest pairs first; ties by (i, j)
        pairs = zip(dd[order], ii[order].tolist(), jj[order].tolist(), strict=True)
        used_i, used_j = set(), set()
        for _, i, j in pairs:
            if i in used_i or j in used_j:
                continue
            used_i.add(i)
            used_j.add(j)
            seen_t[i].append(t_k)
            seen_c[i].append(past_c[j])
    tracks = []
    voxel = float(grid.voxel_size[0])
    for (cls, cells, c), times, cents in zip(current, seen_t, seen_c):
        times, cents = np.array(times), np.array(cents)
        vel = fit_velocity(times, cents)
        span = float(times[0] - times[-1])
        moving = bool(span > 0 and np.hypot(*vel) * span >= min_shift_voxels * voxel)
        tracks.append(
            MoverTrack(cls, cells, c, times, cents, vel if moving else np.zeros(2), moving)
        )
    return tracks
