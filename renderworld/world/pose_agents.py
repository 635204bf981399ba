"""The other road users as the pose head reads them: tracked positions and velocities.

The pose head's bird's-eye view says where the road users are, pooled to a few cells; it does
not say how fast they move, so a lead car braking looks like one cruising. :func:`agent_features`
hands the head the :mod:`renderworld.world.tracks` state of the nearest movers instead: where
each is, its velocity over the whole history and over its last second (their difference is its
braking), whether it is a vulnerable road user. History only: nothing here reads the future.

Frames: the current ego frame (x forward, y left; metres, m/s).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import torch

from renderworld.constants import KEYFRAME_DT, VULNERABLE_CLASS_IDS, GridSpec
from renderworld.world.tracks import MoverTrack, fit_velocity, track_movers

__all__ = ["AGENT_FEATURES", "agent_features", "agent_rows"]

#: Values per agent: x / 20, y / 20, vx / 10, vy / 10 (whole history), vx / 10, vy / 10 (last
#: second), vulnerable road user, present.
AGENT_FEATURES = 8
#: Seconds of history the recent velocity is fitted over.
RECENT_S = 1.0
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
    if history.dim() != 5 or tuple(history_poses.shape) != (*history.shape[:2], 3):
        raise ValueError(
            f"history/history_poses: expected [B, H, X, Y, Z] and [B, H, 3], got "
            f"{tuple(history.shape)} and {tuple(getattr(history_poses, 'shape', ()))}"
        )
    if not isinstance(k, int) or k < 1:
        raise ValueError(f"k: expected an int >= 1, got {k!r}")
    occ = history.detach().cpu().to(torch.int16).numpy()
    poses = history_poses.detach().cpu().double().numpy()
    rows = []
    for i in range(occ.shape[0]):
        h = hashlib.blake2b(occ[i].tobytes(), digest_size=16)
        h.update(poses[i].tobytes() + np.array([k, dt]).tobytes())
        key = h.digest()
        hit = _CACHE.get(key)
        if hit is None:
            hit = agent_rows(track_movers(occ[i], poses[i], grid, dt), k).reshape(-1)
            _CACHE[key] = hit
            if len(_CACHE) > _CACHE_SIZE:
                _CACHE.popitem(last=False)
        rows.append(hit)
    return torch.from_numpy(np.stack(rows)).to(history_poses.device)
