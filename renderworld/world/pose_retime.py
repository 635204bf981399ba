"""How far along its path the ego gets: the pose head's plan retimed by what lies ahead.

A driver brakes for the car ahead or for someone stepping in, and keeps the road's path all the
same. :class:`LeaderRetiming` reads the ego's history and the
:func:`~renderworld.world.pose_agents.leader_features` (the road user in its corridor, the first
one foreseen to enter it) and scales, per command and future step, the arc length the plan has
covered; :func:`retime_along_path` moves each pose to that arc length along the plan's own
polyline. The path's shape, and so the headings the forecast's warp depends on, stays the head's.

Poses are (x, y, yaw) in the current ego frame (metres, radians); the path starts at the origin.
"""

from __future__ import annotations

import torch
from torch import nn

from renderworld.constants import COMMANDS

__all__ = ["LeaderRetiming", "retime_along_path"]

#: Bounds of the log progress factor: the plan may be slowed to a stop, sped up by at most e.
LOG_FACTOR_RANGE = (-6.0, 1.0)


def retime_along_path(poses: torch.Tensor, factors: torch.Tensor) -> torch.Tensor:
    """Each pose moved to ``factor`` times its arc length along the path (linear between poses,
    the last segment carried on beyond the end).

    Args:
        poses: [..., S, 3] (x, y, yaw), a path from the origin (pose 0 at (0, 0, 0) implied).
        factors: [..., S] non-negative progress factors (1: unchanged).

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
        """[B, len(COMMANDS), S] progress factors in (e^-6, e].

        Args:
            history_feats: [B, 4 H] the pose head's history features.
            command_onehot: [B, len(COMMANDS)].
            leader: [B, leader_in] the leader features.
        """
        x = torch.cat([history_feats, command_onehot, leader.float()], dim=1)
        out = self.mlp(x).view(x.shape[0], len(COMMANDS), self.steps)
        return torch.exp(out.clamp(*LOG_FACTOR_RANGE))
