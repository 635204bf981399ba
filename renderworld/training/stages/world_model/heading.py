"""Heading error of the world-model evaluation's planners: counts per rank, metrics of sums.

A planner has a heading when its plan carries one (the pose head's poses, constant turn rate;
constant velocity keeps the current heading, so its error is how much the ego really turns).
The counts are those of :func:`renderworld.metrics.heading.heading_counts` as float64 tensors
that the evaluation loop sums over ranks.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from renderworld.metrics.forecast import horizon_steps
from renderworld.metrics.heading import HEADING_BINS, heading_counts, heading_from_counts
from renderworld.training.stages.world_model.splits import horizon_name

__all__ = ["add_heading_stats", "empty_heading_stats", "heading_from_stats"]


def empty_heading_stats(
    planners, steps: int, device: torch.device, prefix: str = ""
) -> dict[str, torch.Tensor]:
    """Zero ``<prefix><planner>/heading/{hist [S, HEADING_BINS], sum [S], count [S]}``."""
    out = {}
    for p in planners:
        key = f"{prefix}{p}/heading"
        out[f"{key}/hist"] = torch.zeros(steps, HEADING_BINS, dtype=torch.float64, device=device)
        out[f"{key}/sum"] = torch.zeros(steps, dtype=torch.float64, device=device)
        out[f"{key}/count"] = torch.zeros(steps, dtype=torch.float64, device=device)
    return out


def add_heading_stats(
    stats: dict[str, torch.Tensor],
    headings: Mapping[str, torch.Tensor],
    gt_yaw: torch.Tensor,
    valid: torch.Tensor,
    prefix: str = "",
) -> None:
    """Add each planner's [B, S] planned yaw (radians) vs ``gt_yaw`` [B, S] on ``valid``."""
    for p, yaw in headings.items():
        parts = heading_counts(yaw.detach(), gt_yaw.detach(), valid.detach().bool())
        for name, value in zip(("hist", "sum", "count"), parts):
            key = f"{prefix}{p}/heading/{name}"
            stats[key] += torch.from_numpy(value).to(stats[key].device)


def heading_from_stats(
    stats: Mapping[str, torch.Tensor], key: str, horizons_s: tuple[float, ...]
) -> dict[str, float]:
    """``heading_median_<h>`` / ``heading_mean_<h>`` (degrees) of ``<key>/heading/...`` sums."""

    def arr(name: str):
        return stats[f"{key}/heading/{name}"].detach().cpu().double().numpy()

    res = heading_from_counts(arr("hist"), arr("sum"), arr("count"), horizon_steps(horizons_s))
    out = {}
    for i, h in enumerate(horizons_s):
        for what in ("median", "mean"):
            out[f"heading_{what}_{horizon_name(h)}"] = res[what][i]
    return out
