"""Temporal world model: scene tokens + ego tokens -> next-frame tokens and ego motion.

See :mod:`renderworld.world.config` for the displacement/trajectory convention.
"""

from renderworld.world.baselines import (
    constant_turn_rate_poses,
    constant_turn_rate_trajectory,
    constant_velocity_trajectory,
    copy_paste_forecast,
    warp_along_poses,
    warp_constant_velocity_forecast,
)
from renderworld.world.config import WorldModelConfig
from renderworld.world.ego import (
    command_from_trajectory,
    command_indices,
    displacements_from_poses,
    frame_poses_from_poses,
)
from renderworld.world.loss import WorldModelTargets, teacher_forcing_split, world_model_loss
from renderworld.world.model import WorldModel, WorldModelCache, WorldModelOutput, ego_features
from renderworld.world.movers import gt_movers_reference, object_constant_velocity_forecast
from renderworld.world.rollout import RolloutOutput, rollout

__all__ = [
    "RolloutOutput",
    "WorldModel",
    "WorldModelCache",
    "WorldModelConfig",
    "WorldModelOutput",
    "WorldModelTargets",
    "command_from_trajectory",
    "command_indices",
    "constant_turn_rate_poses",
    "constant_turn_rate_trajectory",
    "constant_velocity_trajectory",
    "copy_paste_forecast",
    "displacements_from_poses",
    "ego_features",
    "frame_poses_from_poses",
    "gt_movers_reference",
    "object_constant_velocity_forecast",
    "rollout",
    "teacher_forcing_split",
    "warp_along_poses",
    "warp_constant_velocity_forecast",
    "world_model_loss",
]
