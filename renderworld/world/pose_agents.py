"""The other road users as the pose head reads them: tracked positions and velocities.

The pose head's bird's-eye view says where the road users are, pooled to a few cells; it does
not say how fast they move, so a lead car braking looks like one cruising. :func:`agent_features`
hands the head the :mod:`renderworld.world.tracks` state of the nearest movers instead: where
each is, its velocity over the whole history and over its last second (their difference is its
braking), whether it is a vulnerable road user. :func:`leader_features` hands it two road users
only, those a driver brakes for: the nearest one in the ego's corridor ahead, and the first one
whose last second's velocity carries it into that corridor within 3 s (a car cutting in, a
pedestrian stepping off the kerb). History only: nothing here reads the future.

Frames: the current ego frame (x forward, y left; metres, m/s).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import torch

from renderworld.constants import KEYFRAME_DT, VULNERABLE_CLASS_IDS, GridSpec
from renderworld.world.tracks import MoverTrack, fit_velocity, track_movers

__all__ = [
    "AGENT_FEATURES",
    "LEADER_FEATURES",
    "agent_features",
    "agent_rows",
    "corridor_coords",
    "path_curvature",
    "road_user_inputs",
    "leader_features",
    "leader_row",
]

#: Values per agent: x / 20, y / 20, vx / 10, vy / 10 (whole history), vx / 10, vy / 10 (last
#: second), vulnerable road user, present.
AGENT_FEATURES = 8
#: Seconds of history the recent velocity is fitted over.
RECENT_S = 1.0
#: Values of :func:`leader_row`: the leader's present, s / 20, v_along / 10 (whole history),
#: v_along / 10 (last second), lateral offset / 2, vulnerable road user; then the entering one's
#: present, entry time / 3, s at entry / 20, vulnerable road user.
LEADER_FEATURES = 10
#: Half width of the ego's corridor, metres (half the ego, half a car, a little room).
CORRIDOR_HALF_M = 2.0
#: How far ahead along the corridor a road user counts, metres.
CORRIDOR_AHEAD_M = 40.0
#: Seconds ahead a road user's entry into the corridor is looked for, and the step.
ENTRY_HORIZON_S, ENTRY_STEP_S = 3.0, 0.25
#: Largest path curvature the corridor follows, 1/m (a 10 m radius).
MAX_CURVATURE = 0.1
_CACHE: OrderedDict[bytes, np.ndarray] = OrderedDict()
_CACHE_SIZE = 50_000


def agent_rows(tracks: list[MoverTrack], k: int) -> np.ndarray:
    """[k, AGENT_FEATURES] float32 rows of the ``k`` tracks nearest the ego (zeros beyond).

    A track that does not move (:attr:`MoverTrack.moving` false) gets zero velocities, as the
    forecast treats it.
    """
    out = np.zeros((k, AGENT_FEATURES), dtype=np.float32)
    order = sorted(range(len(tracks)), key=lambda i: float(np.hypot(*tracks[i].centroid)))
    for row, i in enumerate(order[:k]):
        tr = tracks[i]
        recent = tr.times >= -RECENT_S - 1e-6
        v_all = tr.velocity
        v_now = fit_velocity(tr.times[recent], tr.centroids[recent]) if tr.moving else np.zeros(2)
        out[row] = (*(tr.centroid / 20.0), *(v_all / 10.0), *(v_now / 10.0),
                    float(tr.cls in VULNERABLE_CLASS_IDS), 1.0)  # fmt: skip
    return out


def corridor_coords(xy: np.ndarray, curvature: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc length ``s`` and signed lateral offset (left positive) of points [..., 2] from the arc
    that leaves the origin along +x with ``curvature`` (1/m, left positive); metres.

    Points behind the origin get ``s`` <= 0; on a curve, ``s`` wraps at a half turn.
    """
    x, y = xy[..., 0], xy[..., 1]
    if abs(curvature) < 1e-4:
        return x, y
    r = 1.0 / curvature
    sign = np.sign(curvature)
    rho = np.hypot(x, y - r)
    phi = np.arctan2(x, sign * (r - y))
    return abs(r) * phi, sign * (abs(r) - rho)


def path_curvature(poses: np.ndarray) -> float:
    """The curvature (1/m) of the last history step, clipped to :data:`MAX_CURVATURE`; 0 when
    the ego moved under half a metre."""
    step = poses[-1, :2] - poses[-2, :2]
    dist = float(np.hypot(*step))
    if dist < 0.5:
        return 0.0
    dyaw = float(
        np.arctan2(np.sin(poses[-1, 2] - poses[-2, 2]), np.cos(poses[-1, 2] - poses[-2, 2]))
    )
    return float(np.clip(dyaw / dist, -MAX_CURVATURE, MAX_CURVATURE))


def leader_row(tracks: list[MoverTrack], history_poses: np.ndarray) -> np.ndarray:
    """[LEADER_FEATURES] float32: the corridor's leader and the first road user to enter it.

    The corridor is the ego's path ahead at its last history step's curvature
    (:func:`corridor_coords`), :data:`CORRIDOR_HALF_M` to each side and
    :data:`CORRIDOR_AHEAD_M` long. The leader is the track in it with the smallest arc length,
    standing ones included (a parked car in the lane); the entering one is, among the moving
    tracks outside it, the one whose centroid, carried on at its last second's velocity, is in
    it first (every :data:`ENTRY_STEP_S` up to :data:`ENTRY_HORIZON_S`). Velocities are taken
    along the path's heading at the track's place. Zeros where there is none.

    Args:
        tracks: :func:`~renderworld.world.tracks.track_movers` of one history.
        history_poses: [H, 3] (x, y, yaw) of the history frames, current ego frame.
    """
    out = np.zeros(LEADER_FEATURES, dtype=np.float32)
    kappa = path_curvature(np.asarray(history_poses, dtype=np.float64))
    best_s, best_t = np.inf, np.inf
    steps = np.arange(1, int(round(ENTRY_HORIZON_S / ENTRY_STEP_S)) + 1) * ENTRY_STEP_S
    for tr in tracks:
        s, lat = corridor_coords(np.asarray(tr.centroid, dtype=np.float64), kappa)
        s, lat = float(s), float(lat)
        vru = float(tr.cls in VULNERABLE_CLASS_IDS)
        if 0.0 < s <= CORRIDOR_AHEAD_M and abs(lat) < CORRIDOR_HALF_M:
            if s < best_s:
                best_s = s
                head = kappa * s
                along = np.array([np.cos(head), np.sin(head)])
                recent = tr.times >= -RECENT_S - 1e-6
                v_now = (
                    fit_velocity(tr.times[recent], tr.centroids[recent])
                    if tr.moving
                    else np.zeros(2)
                )
                out[:6] = (1.0, s / 20.0, float(tr.velocity @ along) / 10.0,
                           float(v_now @ along) / 10.0, lat / 2.0, vru)  # fmt: skip
            continue
        if not tr.moving:
            continue
        recent = tr.times >= -RECENT_S - 1e-6
        v_now = fit_velocity(tr.times[recent], tr.centroids[recent])
        path = tr.centroid[None] + steps[:, None] * v_now[None]
        ps, pl = corridor_coords(path, kappa)
        inside = np.flatnonzero(
            (ps > 0.0) & (ps <= CORRIDOR_AHEAD_M) & (np.abs(pl) < CORRIDOR_HALF_M)
        )
        if len(inside) and steps[inside[0]] < best_t:
            best_t = float(steps[inside[0]])
            out[6:] = (1.0, best_t / ENTRY_HORIZON_S, float(ps[inside[0]]) / 20.0, vru)
    return out


def _cached_rows(history, history_poses, grid, dt, tag, rows) -> torch.Tensor:
    """``rows(tracks, poses)`` of each history's tracks, [B, F] on ``history_poses``' device;
    cached by a digest of the history's bytes and ``tag``."""
    occ = history.detach().cpu().to(torch.int16).numpy()
    poses = history_poses.detach().cpu().double().numpy()
    out = []
    for i in range(occ.shape[0]):
        h = hashlib.blake2b(occ[i].tobytes(), digest_size=16)
        h.update(poses[i].tobytes() + np.array([dt]).tobytes() + tag)
        key = h.digest()
        hit = _CACHE.get(key)
        if hit is None:
            hit = rows(track_movers(occ[i], poses[i], grid, dt), poses[i]).reshape(-1)
            _CACHE[key] = hit
            if len(_CACHE) > _CACHE_SIZE:
                _CACHE.popitem(last=False)
        out.append(hit)
    return torch.from_numpy(np.stack(out)).to(history_poses.device)


def _check_history(history: torch.Tensor, history_poses: torch.Tensor) -> None:
    if history.dim() != 5 or tuple(history_poses.shape) != (*history.shape[:2], 3):
        raise ValueError(
            f"history/history_poses: expected [B, H, X, Y, Z] and [B, H, 3], got "
            f"{tuple(history.shape)} and {tuple(getattr(history_poses, 'shape', ()))}"
        )


def leader_features(
    history: torch.Tensor,
    history_poses: torch.Tensor,
    grid: GridSpec,
    dt: float = KEYFRAME_DT,
) -> torch.Tensor:
    """[B, LEADER_FEATURES] float32 :func:`leader_row` of each history, on ``history_poses``'
    device (tracked on the CPU, cached as :func:`agent_features`).

    Args:
        history: [B, H, X, Y, Z] integer Occ3D labels, frame j in its own ego frame.
        history_poses: [B, H, 3] (x, y, yaw) of frame j in the current ego frame.
        grid: the occupancy grid.
        dt: seconds between history frames.

    Raises:
        ValueError: naming the arguments on a shape mismatch.
    """
    _check_history(history, history_poses)
    return _cached_rows(history, history_poses, grid, dt, b"leader", leader_row)


def agent_features(
    history: torch.Tensor,
    history_poses: torch.Tensor,
    grid: GridSpec,
    k: int,
    dt: float = KEYFRAME_DT,
) -> torch.Tensor:
    """The ``k`` nearest tracked movers of each history, flattened for :class:`PoseHead`.

    Tracking runs on the CPU (:func:`~renderworld.world.tracks.track_movers`); results are
    cached by a digest of the history's bytes, so a training that revisits its windows tracks
    each once.

    Args:
        history: [B, H, X, Y, Z] integer Occ3D labels, frame j in its own ego frame.
        history_poses: [B, H, 3] (x, y, yaw) of frame j in the current ego frame.
        grid: the occupancy grid.
        k: how many movers (nearest first).
        dt: seconds between history frames.

    Returns:
        [B, k * AGENT_FEATURES] float32 on ``history_poses``' device (rows of
        :func:`agent_rows`, nearest first).

    Raises:
        ValueError: naming the argument on a shape mismatch or ``k < 1``.
    """
    _check_history(history, history_poses)
    if not isinstance(k, int) or k < 1:
        raise ValueError(f"k: expected an int >= 1, got {k!r}")
    return _cached_rows(history, history_poses, grid, dt, b"agents%d" % k,
                        lambda tracks, _poses: agent_rows(tracks, k))  # fmt: skip


def road_user_inputs(
    head, history: torch.Tensor | None, history_poses: torch.Tensor, grid: GridSpec | None
) -> torch.Tensor | None:
    """The ``agents`` input of a pose head (or ensemble): :func:`agent_features` of its
    ``agents`` movers, then :func:`leader_features` when it reads the ``leader``; None when
    it reads neither.

    Raises:
        ValueError: naming ``history`` when the head reads them and it or ``grid`` is missing.
    """
    if not (head.agents or head.leader):
        return None
    if history is None or grid is None:
        raise ValueError(
            f"history: the pose head reads agents={head.agents}, leader={head.leader}; pass the "
            "history frames and their grid"
        )
    parts = [agent_features(history, history_poses, grid, head.agents)] if head.agents else []
    if head.leader:
        parts.append(leader_features(history, history_poses, grid))
    return torch.cat(parts, dim=1)
