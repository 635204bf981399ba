"""What the pose head reads: the history in the current ego frame, bird's-eye views, kinematics.

Poses are (x, y, yaw) of an ego frame in the current ego frame (metres, radians; x forward,
y left), as :func:`renderworld.world.ego.frame_poses_from_poses` gives them.
"""

from __future__ import annotations

import torch

from renderworld.constants import FREE_ID, GridSpec
from renderworld.world.baselines import warp_along_poses

__all__ = [
    "BEV_GROUPS",
    "align_history",
    "bev_channels",
    "invert_poses",
    "kinematic_features",
    "motion_channels",
    "jittered_history",
    "steady_history",
]


#: Occ3D class ids of each bird's-eye-view channel: driveable surface, other flat, sidewalk,
#: terrain, manmade, vegetation, objects (others + the ten object classes).
BEV_GROUPS: tuple[tuple[int, ...], ...] = (
    (11,),
    (12,),
    (13,),
    (14,),
    (15,),
    (16,),
    tuple(range(11)),
)


def bev_channels(occupancy: torch.Tensor) -> torch.Tensor:
    """Bird's-eye view of class groups: a channel is 1 where any z level holds its classes.

    Args:
        occupancy: [B, X, Y, Z] integer Occ3D labels.

    Returns:
        [B, len(BEV_GROUPS), X, Y] float32.
    """
    if not isinstance(occupancy, torch.Tensor) or occupancy.dim() != 4:
        raise ValueError(
            f"occupancy: expected a [B, X, Y, Z] tensor, got {getattr(occupancy, 'shape', None)}"
        )
    occ = occupancy.long()
    chans = [torch.zeros(occ.shape[:3], dtype=torch.bool, device=occ.device) for _ in BEV_GROUPS]
    for c, ids in enumerate(BEV_GROUPS):
        for i in ids:
            chans[c] |= (occ == i).any(dim=-1)
    return torch.stack(chans, dim=1).float()


def motion_channels(
    history: torch.Tensor, history_poses: torch.Tensor, grid: GridSpec, frames: int
) -> torch.Tensor:
    """Where the road users were: the object channel of the last ``frames`` history frames
    before the current one, each brought into the current ego frame with its pose.

    Static objects land where they are now; a road user leaves a trail whose spacing is its
    speed relative to the ground, and whose change is its braking.

    Args:
        history: [B, H, X, Y, Z] integer Occ3D labels, frame j in its own ego frame.
        history_poses: [B, H, 3] (x, y, yaw) of frame j in the current ego frame.
        grid: the occupancy grid.
        frames: how many frames before the current one (t-1, t-2, ...), < H.

    Returns:
        [B, frames, X, Y] float32: the objects channel of :func:`bev_channels` (classes 0-10) of
        each frame, t-1 first.
    """
    if history.dim() != 5 or tuple(history_poses.shape) != (*history.shape[:2], 3):
        raise ValueError(
            f"history/history_poses: expected [B, H, X, Y, Z] and [B, H, 3], got "
            f"{tuple(history.shape)} and {tuple(getattr(history_poses, 'shape', ()))}"
        )
    h = history.shape[1]
    if not 0 < frames < h:
        raise ValueError(f"frames: expected 1..{h - 1} (H = {h}), got {frames}")
    idx = list(range(h - 2, h - 2 - frames, -1))  # t-1, t-2, ...
    aligned = align_history(history[:, idx], history_poses[:, idx], grid)
    b = aligned.shape[0]
    return bev_channels(aligned.flatten(0, 1))[:, -1].view(b, frames, *aligned.shape[2:4])


def invert_poses(poses: torch.Tensor) -> torch.Tensor:
    """Pose of frame A in frame B from the pose of B in A.

    Args:
        poses: [..., 3] (x, y, yaw).

    Returns:
        [..., 3]: ``(-R(-yaw) (x, y), -yaw)``.
    """
    if poses.shape[-1] != 3:
        raise ValueError(f"poses: expected [..., 3] (x, y, yaw), got {tuple(poses.shape)}")
    x, y, yaw = poses.unbind(-1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    return torch.stack([-(c * x + s * y), -(-s * x + c * y), -yaw], dim=-1)


def align_history(
    occupancy: torch.Tensor, history_poses: torch.Tensor, grid: GridSpec, fill: int = FREE_ID
) -> torch.Tensor:
    """Bring history frames into the current ego frame with their known poses.

    Args:
        occupancy: [B, H, X, Y, Z] labels, frame j in its own ego frame.
        history_poses: [B, H, 3] (x, y, yaw) of frame j in the current ego frame.
        grid: the occupancy grid.
        fill: label where frame j saw nothing (outside its grid).

    Returns:
        [B, H, X, Y, Z]: frame j resampled on the current frame's grid (the current frame,
        pose zero, comes back unchanged).
    """
    if occupancy.dim() != 5 or tuple(history_poses.shape) != (*occupancy.shape[:2], 3):
        raise ValueError(
            f"occupancy/history_poses: expected [B, H, X, Y, Z] and [B, H, 3], got "
            f"{tuple(occupancy.shape)} and {tuple(history_poses.shape)}"
        )
    b, h = occupancy.shape[:2]
    current_in_j = invert_poses(history_poses.double()).reshape(b * h, 1, 3)
    out = warp_along_poses(occupancy.reshape(b * h, *occupancy.shape[2:]), current_in_j, grid, fill)
    return out.reshape(occupancy.shape)


def kinematic_features(history_poses: torch.Tensor) -> torch.Tensor:
    """Per-step motion of the history on a log-like scale, for :class:`PoseHead`.

    ``asinh(v / s) / 3`` keeps the sign, is linear near zero and logarithmic far from it, so a
    0.3-degree heading change (a turn starting) and a 14-degree one (a turn going on) are both
    clearly apart from zero and from each other.

    Args:
        history_poses: [B, H, 3] (x, y, yaw) of frames t-H+1..t in the current ego frame.

    Returns:
        [B, 4 H - 6] float32: the H-1 step lengths (scale 1 m), their H-2 changes (scale
        1 cm), the H-1 heading changes (scale 0.1 degree) and their H-2 changes (scale 0.1
        degree).
    """
    hp = history_poses.float()
    step = torch.diff(hp[..., :2], dim=1).norm(dim=-1)  # metres per history step
    dyaw = torch.rad2deg(torch.diff(hp[..., 2], dim=1))
    dyaw = torch.remainder(dyaw + 180.0, 360.0) - 180.0
    parts = [step / 1.0, torch.diff(step, dim=1) / 0.01, dyaw / 0.1, torch.diff(dyaw, dim=1) / 0.1]
    return torch.asinh(torch.cat(parts, dim=1)) / 3.0


def steady_history(history_poses: torch.Tensor) -> torch.Tensor:
    """The history the ego would have had driving its last step all along: every earlier step
    repeats the last displacement and heading change (constant speed and turn rate), so the
    current pose, speed and turn rate stay and any trend before them (a slowing, a turn
    starting) is gone. The pose head's past-motion dropout (ChauffeurNet) trains on it.

    Args:
        history_poses: [B, H, 3] (x, y, yaw) of frames t-H+1..t in the current ego frame (the
            last row the origin), H >= 2.

    Returns:
        [B, H, 3], same dtype: row H-1 - k is ``-sum_{j<k} R(-j w) d``, yaw ``-k w``, with
        ``d`` the last displacement and ``w`` the last heading change.
    """
    if history_poses.dim() != 3 or history_poses.shape[-1] != 3 or history_poses.shape[1] < 2:
        raise ValueError(f"history_poses: expected [B, H>=2, 3], got {tuple(history_poses.shape)}")
    q = history_poses.double()
    h = q.shape[1]
    d = q[:, -1, :2] - q[:, -2, :2]  # [B, 2]
    w = torch.remainder(q[:, -1, 2] - q[:, -2, 2] + torch.pi, 2 * torch.pi) - torch.pi
    j = torch.arange(h - 1, dtype=torch.float64, device=q.device)  # steps back: 0 .. H-2
    ang = -w[:, None] * j  # [B, H-1]: heading of the step k+1 back, relative to the last one
    c, s = torch.cos(ang), torch.sin(ang)
    step_x = c * d[:, None, 0] - s * d[:, None, 1]
    step_y = s * d[:, None, 0] + c * d[:, None, 1]
    back = -torch.stack([step_x.cumsum(1), step_y.cumsum(1)], -1)  # [B, H-1, 2]: t-1, t-2, ...
    yaw = -w[:, None] * (j + 1.0)
    past = torch.cat([back, yaw[..., None]], -1).flip(1)  # t-H+1 .. t-1
    out = torch.cat([past, torch.zeros_like(q[:, :1])], 1)
    return out.to(history_poses.dtype)


def jittered_history(history_poses: torch.Tensor, sigma_m: float) -> torch.Tensor:
    """The history with every past position moved by Gaussian noise of ``sigma_m`` per axis
    (the current pose, the origin, and every heading stay): the pose head's history noise
    trains it to read a trend of a few centimetres per step, such as a plan tracked a little
    behind in closed loop, as noise rather than as braking.

    Args:
        history_poses: [B, H, 3] (x, y, yaw) of frames t-H+1..t in the current ego frame (the
            last row the origin).
        sigma_m: standard deviation of the noise, metres (>= 0; 0 returns the input).

    Returns:
        [B, H, 3], same dtype and device.
    """
    if history_poses.dim() != 3 or history_poses.shape[-1] != 3:
        raise ValueError(f"history_poses: expected [B, H, 3], got {tuple(history_poses.shape)}")
    if not sigma_m >= 0:
        raise ValueError(f"sigma_m: expected a number >= 0, got {sigma_m!r}")
    if sigma_m == 0:
        return history_poses
    noise = torch.randn_like(history_poses[:, :-1, :2]) * sigma_m
    past = torch.cat([history_poses[:, :-1, :2] + noise, history_poses[:, :-1, 2:]], -1)
    return torch.cat([past, history_poses[:, -1:]], 1)
