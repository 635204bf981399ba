"""Straight / turning split of the world-model evaluation: which windows turn, and L2 per split.

The split is for reporting only (it reads the ground-truth future headings, never an input).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from renderworld.constants import KEYFRAME_DT

__all__ = [
    "TURN_THRESHOLD_DEG",
    "turning_windows",
    "add_split_l2",
    "split_l2_from_stats",
    "horizon_name",
]


def horizon_name(h: float) -> str:
    """Metric-key suffix of a horizon in seconds: 1.0 -> ``"1s"``, 0.5 -> ``"0.5s"``."""
    return f"{h:g}s"


#: A window is "turning" when the ego heading of some future frame (t+1..t+S, up to 3 s)
#: differs from the current one by more than this many degrees (ground truth; for reporting
#: only, never an input). On the mini fixture's val split: 18 of 28 windows.
TURN_THRESHOLD_DEG = 5.0


def turning_windows(future_poses: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """[B] bool: windows whose valid future headings turn more than ``TURN_THRESHOLD_DEG``.

    Args:
        future_poses: [B, S, 3] (x, y, yaw) of the future frames in the current ego frame.
        valid: [B, S] bool future frames that exist.
    """
    if future_poses.dim() != 3 or future_poses.shape[-1] != 3:
        raise ValueError(f"future_poses: expected [B, S, 3], got {tuple(future_poses.shape)}")
    if tuple(valid.shape) != tuple(future_poses.shape[:2]):
        raise ValueError(
            f"valid: expected {tuple(future_poses.shape[:2])}, got {tuple(valid.shape)}"
        )
    yaw = torch.atan2(torch.sin(future_poses[..., 2]), torch.cos(future_poses[..., 2])).abs()
    yaw = torch.where(valid.bool(), yaw, torch.zeros_like(yaw))
    return yaw.amax(dim=1) > np.radians(TURN_THRESHOLD_DEG)


def add_split_l2(
    stats: dict[str, torch.Tensor],
    trajectories: Mapping[str, torch.Tensor],
    gt_traj: torch.Tensor,
    valid: torch.Tensor,
    turning: torch.Tensor,
    prefix: str = "",
) -> None:
    """Add per-step L2 sums / counts and window counts of the straight and turning windows.

    Keys ``<prefix><planner>/<split>/l2_sum`` [S], ``.../l2_count`` [S], ``.../windows`` [].

    Args:
        trajectories: ``{planner: [B, S, 2]}`` metres, current ego frame.
        gt_traj: [B, S, 2] metres.
        valid: [B, S] bool.
        turning: [B] bool (:func:`turning_windows`).
    """
    for p, traj in trajectories.items():
        err = torch.linalg.norm(traj.double() - gt_traj.double().to(traj.device), dim=-1)
        ok = valid.to(traj.device).bool()
        t = turning.to(traj.device).bool()
        for split, sel in (("straight", ~t), ("turning", t)):
            m = ok & sel[:, None]
            for name, value in (
                ("l2_sum", torch.where(m, err, torch.zeros_like(err)).sum(0)),
                ("l2_count", m.double().sum(0)),
                ("windows", sel.double().sum()),
            ):
                key = f"{prefix}{p}/{split}/{name}"
                v = value.to(torch.float64)
                stats[key] = stats[key] + v.to(stats[key].device) if key in stats else v


def split_l2_from_stats(
    stats: Mapping[str, torch.Tensor], key: str, horizons_s: tuple[float, ...]
) -> dict[str, float]:
    """``l2_at_horizon_<h>`` (+ ``_avg``) metres and ``num_windows`` of one split's sums."""
    s = stats[f"{key}/l2_sum"].detach().cpu().double().numpy()
    n = stats[f"{key}/l2_count"].detach().cpu().double().numpy()
    out: dict[str, float] = {"num_windows": float(stats[f"{key}/windows"])}
    vals = []
    for h in horizons_s:
        k = int(round(h / KEYFRAME_DT))
        v = float(s[k - 1] / n[k - 1]) if n[k - 1] else float("nan")
        out[f"l2_at_horizon_{horizon_name(h)}"] = v
        vals.append(v)
    out["l2_at_horizon_avg"] = float(np.mean(vals))
    return out
