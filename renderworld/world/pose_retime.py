"""How far along its path the ego gets: the pose head's plan retimed by what lies ahead.

A driver brakes for the car ahead or for someone stepping in, and keeps the road's path all the
same. :class:`LeaderRetiming` reads the ego's history and the
:func:`~renderworld.world.pose_agents.leader_features` (the road user in its corridor, the first
one foreseen to enter it) and scales, per command and future step, the arc length the plan has
covered; :func:`retime_along_path` moves each pose to that arc length along the plan's own
polyline. The path's shape, and so the headings the forecast's warp depends on, stays the head's.

:func:`stop_behind_leaders` is the same retiming by a rule instead of a network: where the car
ahead in the corridor brakes hard or has come to a stand, the plan stops behind it at constant
deceleration (``PoseWarpWorldModel(leader_stop=True)``, at prediction time only); with
``entering`` it also slows for road users foreseen to enter the corridor ahead of the ego.

Poses are (x, y, yaw) in the current ego frame (metres, radians); the path starts at the origin.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from renderworld.constants import COMMANDS, EGO_CENTRE_OFFSET, EGO_LENGTH, KEYFRAME_DT, GridSpec
from renderworld.world.pose_agents import (
    CORRIDOR_AHEAD_M,
    CORRIDOR_HALF_M,
    ENTRY_HORIZON_S,
    ENTRY_STEP_S,
    RECENT_S,
    corridor_coords,
    path_curvature,
)
from renderworld.world.tracks import MoverTrack, fit_velocity, track_movers

__all__ = [
    "LeaderRetiming",
    "last_step_speed",
    "leader_stop_factors",
    "leader_stop_room",
    "retime_along_path",
    "stop_behind_leaders",
    "stop_profile",
]

#: Bounds of the log progress factor: the plan may be slowed to a stop, sped up by at most e.
LOG_FACTOR_RANGE = (-6.0, 1.0)


def retime_along_path(poses: torch.Tensor, factors: torch.Tensor) -> torch.Tensor:
    """Each pose moved to ``factor`` times its arc length along the path (linear between poses,
    the last segment carried on beyond the end).

    Args:
        poses: [..., S, 3] (x, y, yaw), a path from the origin (pose 0 at (0, 0, 0) implied).
        factors: [..., S] non-negative progress factors (1: the same place, up to rounding).

    Returns:
        [..., S, 3] retimed poses; yaw interpolated like the positions (unwrapped); a plan
        that stands is returned as it is.

    Raises:
        ValueError: naming the argument on a shape mismatch.
    """
    if poses.shape[-1] != 3 or tuple(factors.shape) != tuple(poses.shape[:-1]):
        raise ValueError(
            f"poses/factors: expected [..., S, 3] and [..., S], got {tuple(poses.shape)} and "
            f"{tuple(factors.shape)}"
        )
    zero = torch.zeros_like(poses[..., :1, :])
    pts = torch.cat([zero, poses], dim=-2)  # [..., S+1, 3]
    yaw = pts[..., 2]
    # Unwrap the yaw so that interpolation does not cross the +-pi cut.
    d = torch.diff(yaw, dim=-1)
    d = torch.atan2(torch.sin(d), torch.cos(d))
    pts = torch.cat([pts[..., :2], torch.cat([yaw[..., :1], yaw[..., :1] + d.cumsum(-1)], -1)
                     .unsqueeze(-1)], dim=-1)  # fmt: skip
    seg = torch.linalg.vector_norm(torch.diff(pts[..., :2], dim=-2), dim=-1)  # [..., S]
    cum = torch.cat([torch.zeros_like(seg[..., :1]), seg.cumsum(-1)], dim=-1)  # [..., S+1]
    target = factors * cum[..., 1:]
    n = seg.shape[-1]
    j = torch.searchsorted(cum.detach().contiguous(), target.detach().contiguous(), right=True)
    j = j.clamp(1, n)  # segment j runs from point j-1 to point j; beyond the end: the last
    lo = cum.gather(-1, j - 1)
    length = seg.gather(-1, j - 1)
    t = (target - lo) / length.clamp_min(1e-6)
    t = torch.where(length > 1e-6, t, torch.zeros_like(t))
    idx = (j - 1).unsqueeze(-1).expand(*j.shape, 3)
    p0 = pts.gather(-2, idx)
    p1 = pts.gather(-2, idx + 1)
    out = p0 + t.unsqueeze(-1) * (p1 - p0)
    # A plan that stands (under a millimetre in all) has no path to move along: kept as it is.
    still = (cum[..., -1:] < 1e-3).unsqueeze(-1)
    return torch.where(still, poses, out)


class LeaderRetiming(nn.Module):
    """Progress factors per command and step from the history and the leader features.

    Its last layer starts at zero: an untrained module leaves every plan as it is.

    Args:
        history: H history frames.
        steps: S future frames.
        leader_in: width of the leader features.
        hidden: width of the MLP.
    """

    def __init__(self, history: int, steps: int, leader_in: int, hidden: int = 64):
        super().__init__()
        self.steps = steps
        n_in = 4 * history + len(COMMANDS) + leader_in
        self.mlp = nn.Sequential(
            nn.Linear(n_in, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(),
            nn.Linear(hidden, len(COMMANDS) * steps),
        )  # fmt: skip
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, history_feats: torch.Tensor, command_onehot: torch.Tensor,
                leader: torch.Tensor) -> torch.Tensor:  # fmt: skip
        """[B, len(COMMANDS), S] progress factors in [e^-6, e].

        Args:
            history_feats: [B, 4 H] the pose head's history features.
            command_onehot: [B, len(COMMANDS)].
            leader: [B, leader_in] the leader features.
        """
        x = torch.cat([history_feats, command_onehot, leader.float()], dim=1)
        out = self.mlp(x).view(x.shape[0], len(COMMANDS), self.steps)
        return torch.exp(out.clamp(*LOG_FACTOR_RANGE))


def stop_profile(
    plan_s: np.ndarray, v0: float, room: float, dt: float, v_lead: float = 0.0
) -> np.ndarray:
    """[S] arc lengths: the plan's ``plan_s`` [S] capped by a constant deceleration from ``v0``
    (m/s) to ``v_lead`` that ends ``room`` metres ahead of where a leader moving on at ``v_lead``
    started (with ``v_lead`` 0, a stop at ``room``; the ego stands where ``room`` <= 0 or ``v0`` <=
    0, and keeps behind the leader's motion where ``v_lead`` > 0; where the stop takes longer than
    the horizon the plan ends short of ``room``), future step k at (k + 1) dt."""
    t = (np.arange(len(plan_s)) + 1) * dt
    lead = room + v_lead * t
    if room <= 0.0 or v0 <= v_lead:
        if v_lead <= 0.0:
            return np.zeros_like(plan_s)
        return np.minimum(plan_s, np.maximum(lead, 0.0))
    decel = (v0 - v_lead) ** 2 / (2.0 * room)
    t_end = (v0 - v_lead) / decel
    brake = np.where(t < t_end, v0 * t - 0.5 * decel * t * t, lead)
    return np.minimum(plan_s, brake)


def _extent_along(tr: MoverTrack, grid: GridSpec, kappa: float) -> tuple[float, float]:
    """(first, last) arc length (m) of a track's cells along the corridor, half a cell out."""
    ix, iy = np.nonzero(tr.cells)
    cx = grid.range_min[0] + (ix + 0.5) * grid.voxel_size[0]
    cy = grid.range_min[1] + (iy + 0.5) * grid.voxel_size[1]
    cs, _ = corridor_coords(np.stack([cx, cy], -1), kappa)
    half = 0.5 * float(grid.voxel_size[0])
    if not len(cs):
        s = float(corridor_coords(np.asarray(tr.centroid, float), kappa)[0])
        return s - half, s + half
    return float(cs.min()) - half, float(cs.max()) + half


def _entering(tr: MoverTrack, kappa: float) -> tuple[float, float, float] | None:
    """(entry time s, arc length m at entry, speed along the path there m/s, >= 0) of a moving
    track outside the corridor that its last second's velocity carries into it within
    :data:`ENTRY_HORIZON_S`; None when it does not enter."""
    recent = tr.times >= -RECENT_S - 1e-6
    v = fit_velocity(tr.times[recent], tr.centroids[recent])
    steps = np.arange(1, int(round(ENTRY_HORIZON_S / ENTRY_STEP_S)) + 1) * ENTRY_STEP_S
    ps, pl = corridor_coords(tr.centroid[None] + steps[:, None] * v[None], kappa)
    inside = np.flatnonzero((ps > 0.0) & (ps <= CORRIDOR_AHEAD_M) & (np.abs(pl) < CORRIDOR_HALF_M))
    if not len(inside):
        return None
    s_e = float(ps[inside[0]])
    head = kappa * s_e
    return float(steps[inside[0]]), s_e, max(float(v @ (np.cos(head), np.sin(head))), 0.0)


def last_step_speed(history_poses: np.ndarray, dt: float = KEYFRAME_DT) -> float:
    """The ego's speed over its last history step (m/s), the speed the stop starts from."""
    hist = np.asarray(history_poses, dtype=np.float64)
    return float(np.hypot(*(hist[-1, :2] - hist[-2, :2]))) / dt


def leader_stop_room(
    tracks: list[MoverTrack],
    history_poses: np.ndarray,
    grid: GridSpec,
    gap: float = 2.0,
    min_decel: float = 2.0,
) -> float | None:
    """How far along its path (m) the ego may go behind a leader coming to a stop, or None.

    The leader is the nearest road user in the corridor (that of
    :func:`~renderworld.world.pose_agents.leader_row`) that moved over the history and now
    brakes at ``min_decel`` m/s² or more (a quadratic fit of its last 1.5 s along the path) or
    has come to a stand (under 0.5 m/s in any direction) after moving at over 2 m/s (its
    whole-history speed). It is taken to stop at that rate; the room ends ``gap`` metres behind
    where its rear then is, less the ego's front overhang (negative: no room).

    Args:
        tracks: :func:`~renderworld.world.tracks.track_movers` of the history.
        history_poses: [H, 3] the history poses, current ego frame.
        grid: the occupancy grid (cell sizes).
        gap: metres left between the ego's front bumper and the leader's rear.
        min_decel: the least braking (m/s²) that makes a moving leader one.
    """
    kappa = path_curvature(np.asarray(history_poses, dtype=np.float64))
    best = None
    for tr in tracks:
        if not tr.moving:
            continue
        s, lat = (float(v) for v in corridor_coords(np.asarray(tr.centroid, float), kappa))
        if not (0.0 < s <= CORRIDOR_AHEAD_M and abs(lat) < CORRIDOR_HALF_M):
            continue
        if best is not None and s >= best[0]:
            continue
        recent = tr.times >= -1.5 - 1e-6
        if recent.sum() < 3:
            continue
        ts = tr.times[recent]
        along, across = corridor_coords(tr.centroids[recent], kappa)
        c2, c1, _ = np.polyfit(ts, along, 2)
        v_now, accel = float(c1), float(2.0 * c2)
        v_across = float(np.polyfit(ts, across, 2)[1])
        whole = float(np.hypot(*tr.velocity))
        if v_now > 0.5 and accel <= -min_decel:
            travel = v_now * v_now / (2.0 * -accel)
        elif np.hypot(v_now, v_across) <= 0.5 and whole > 2.0:
            travel = 0.0
        else:
            continue
        best = (s, _extent_along(tr, grid, kappa)[0] + travel)
    return None if best is None else best[1] - gap - (EGO_CENTRE_OFFSET + EGO_LENGTH / 2)


def leader_stop_factors(
    poses: np.ndarray,
    tracks: list[MoverTrack],
    history_poses: np.ndarray,
    grid: GridSpec,
    dt: float = KEYFRAME_DT,
    gap: float = 2.0,
    min_decel: float = 2.0,
    entering: bool = False,
) -> np.ndarray:
    """[S] progress factors that stop the plan behind a leader coming to a stop (1: no change).

    When the plan would run past the :func:`leader_stop_room`, it is retimed to a
    constant-deceleration stop there from the ego's speed now (the ego stands where there is no
    room). With ``entering``, also each moving road user that its last second's velocity
    carries into the corridor within 3 s (a car cutting in, a pedestrian stepping off the kerb)
    is taken to go on along the path at its speed along it from there (0 for one crossing);
    where the plan reaches the place after it (the ego's front bumper short of its rear when it
    enters) and would come within ``gap`` of its rear from then on, the plan is retimed to slow
    uniformly to that speed ``gap`` behind it (:func:`stop_profile`). One the ego passes first
    is left to it.

    Args:
        poses: [S, 3] the plan, current ego frame.
        tracks: :func:`~renderworld.world.tracks.track_movers` of the history.
        history_poses: [H, 3] the history poses.
        grid: the occupancy grid (cell sizes).
        dt: seconds between frames.
        gap: metres left between the ego's front bumper and the leader's rear.
        min_decel: the least braking (m/s²) that makes a moving leader one.
        entering: also slow for road users foreseen to enter the corridor.
    """
    hist = np.asarray(history_poses, dtype=np.float64)
    kappa = path_curvature(hist)
    v0 = last_step_speed(hist, dt)
    steps = np.linalg.norm(
        np.diff(np.concatenate([np.zeros((1, 2)), poses[:, :2]]), axis=0), axis=1
    )
    plan_s = np.cumsum(steps)
    t = (np.arange(len(poses)) + 1) * dt
    front = EGO_CENTRE_OFFSET + EGO_LENGTH / 2
    capped = plan_s
    for tr in tracks if entering else ():
        s, lat = (float(v) for v in corridor_coords(np.asarray(tr.centroid, float), kappa))
        if not tr.moving or s <= 0.0 or (s <= CORRIDOR_AHEAD_M and abs(lat) < CORRIDOR_HALF_M):
            continue
        hit = _entering(tr, kappa)
        if hit is None:
            continue
        t_e, s_e, v_u = hit
        room = s_e - v_u * t_e - (s - _extent_along(tr, grid, kappa)[0]) - gap - front
        after = t >= t_e - 1e-6
        second = np.interp(t_e, np.r_[0.0, t], np.r_[0.0, plan_s]) <= room + v_u * t_e + gap
        if second and (plan_s[after] > room + v_u * t[after]).any():
            capped = np.minimum(capped, stop_profile(plan_s, v0, room, dt, v_u))
    room = leader_stop_room(tracks, hist, grid, gap, min_decel)
    if room is not None and plan_s[-1] > max(room, 0.0):
        capped = np.minimum(capped, stop_profile(plan_s, v0, room, dt))
    if (capped >= plan_s).all():
        return np.ones(len(poses))
    return np.where(plan_s > 1e-6, capped / np.maximum(plan_s, 1e-6), 1.0)


def stop_behind_leaders(
    poses: torch.Tensor,
    history: torch.Tensor,
    history_poses: torch.Tensor,
    grid: GridSpec,
    dt: float = KEYFRAME_DT,
    entering: bool = False,
) -> torch.Tensor:
    """Each plan of a batch stopped behind its leader coming to a stop
    (:func:`leader_stop_factors`, tracked on the CPU), the rest unchanged.

    Args:
        poses: [B, S, 3] plans, current ego frame.
        history: [B, H, X, Y, Z] integer labels of the history frames.
        history_poses: [B, H, 3] their poses in the current ego frame.
        grid: the occupancy grid.
        dt: seconds between frames.
        entering: also slow for road users foreseen to enter the corridor.

    Returns:
        [B, S, 3] on ``poses``' device and dtype; a plan the rule does not stop is returned
        bit for bit.
    """
    occ = history.detach().cpu().to(torch.int16).numpy()
    hp = history_poses.detach().cpu().double().numpy()
    plans = poses.detach().cpu().double().numpy()
    factors = []
    for i in range(occ.shape[0]):
        tracks = track_movers(occ[i], hp[i], grid, dt)
        factors.append(leader_stop_factors(plans[i], tracks, hp[i], grid, dt, entering=entering))
    f = torch.as_tensor(np.stack(factors), dtype=poses.dtype, device=poses.device)
    keep = (f == 1.0).all(dim=-1)[:, None, None]  # plans the rule leaves alone: bit for bit
    return torch.where(keep, poses, retime_along_path(poses, f))
