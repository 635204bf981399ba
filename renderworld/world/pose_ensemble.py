"""Several pose heads that read the same inputs; the plan is the mean of theirs.

One pose head's heading where a turn begins depends on its initialisation, and a few such
windows move the forecast's mIoU by points (docs/world_model.md). Heads trained side by side
from different initialisations, each on its own loss, and averaged at prediction time (a deep
ensemble) keep what they agree on and average out what each gets wrong on its own. Poses are
(x, y, yaw) in the current ego frame (metres, radians).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["PoseEnsemble"]

#: What an ensemble takes over from its first member (all members must agree).
SHARED = (
    "history",
    "steps",
    "anchors",
    "kinematics",
    "motion_frames",
    "agents",
    "bev_pool",
    "leader",
)


class PoseEnsemble(nn.Module):
    """The mean of :class:`~renderworld.world.pose.PoseHead` members' predictions.

    It reads and returns what one head does, so a model or planner uses either alike;
    :meth:`members_forward` gives each member's own prediction, for training each on its own
    loss.

    Args:
        members: two or more pose heads with equal :data:`SHARED` settings.

    Raises:
        ValueError: naming ``members`` when there are fewer than two or they disagree.
    """

    def __init__(self, members: Sequence[nn.Module]):
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"members: expected two or more pose heads, got {len(members)}")
        for name in SHARED:
            values = {repr(getattr(m, name)) for m in members}
            if len(values) != 1:
                raise ValueError(f"members: their {name} differ ({sorted(values)})")
            setattr(self, name, getattr(members[0], name))
        self.members = nn.ModuleList(members)

    def members_forward(
        self,
        history_poses: torch.Tensor,
        command: torch.Tensor,
        bev: torch.Tensor,
        agents: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each member's prediction: (poses [K, B, S, 3], modes [K, B, C, S, 3]); inputs as
        :meth:`renderworld.world.pose.PoseHead.forward`."""
        outs = [m(history_poses, command, bev, agents) for m in self.members]
        return torch.stack([o[0] for o in outs]), torch.stack([o[1] for o in outs])

    def forward(self, *inputs: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The members' mean: (poses [B, S, 3], modes [B, C, S, 3]); inputs as
        :meth:`renderworld.world.pose.PoseHead.forward`."""
        poses, modes = self.members_forward(*inputs)
        return poses.mean(0), modes.mean(0)
