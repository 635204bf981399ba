"""Forecasts and plans of the ``world_model`` evaluation: the model's and the baselines'.

:func:`stage_forecast` is :meth:`WorldModelStage.forecast
<renderworld.training.stages.world_model.stage.WorldModelStage.forecast>`: for one setting's
inputs, the model's forecast and plan with the GT-derived command and with the command derived
from the history, its checked plans (pose-warp models), the history-only baselines and the
model's movers under the ground-truth poses (a reference). The stage is passed in (its
settings, grid, tokenizers and token cache).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from renderworld.precision import autocast_off
from renderworld.tokenizer import Tokens
from renderworld.training.stages.world_model import pose_warp as wmp
from renderworld.training.stages.world_model.references import gt_pose_movers_row
from renderworld.training.stages.world_model.report import (
    CHECKED,
    CHECKED_HISTORY_COMMAND,
    HISTORY_COMMAND,
    MODEL_MOVERS,
)
from renderworld.training.stages.world_model.settings import EvalSetting
from renderworld.world import (
    command_indices,
    constant_turn_rate_poses,
    constant_velocity_trajectory,
    copy_paste_forecast,
    object_constant_velocity_forecast,
    warp_along_poses,
    warp_constant_velocity_forecast,
)
from renderworld.world.forecast import movers_of

__all__ = ["stage_forecast", "token_forecast"]


@torch.no_grad()
def stage_forecast(
    stage: Any,
    model: nn.Module,
    batch: dict,
    setting: EvalSetting,
    tokens: torch.Tensor | None,
    headings: dict[str, torch.Tensor] | None = None,
    baselines: bool = True,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Forecasts and plans of the model and the baselines for one setting's inputs.

    Args:
        model: the world model of ``setting`` (unwrapped), on the batch's device.
        batch: a collated batch of :class:`WorldModelWindows` on that device.
        setting: whose history occupancy (``setting.inputs``) is rolled out.
        tokens: codes [B, >=history, G, h, w] of those inputs, or None to encode them.
        headings: if given, filled with ``{planner: [B, S] yaw}`` (radians, current ego
            frame) of the planners whose plan carries a heading.
        baselines: False: the model's rows only (their figures are already known).

    Returns:
        (``{method: [B, S, X, Y, Z] uint8}`` forecasts, ``{method: [B, S, 2]}`` trajectories
        in metres, current ego frame), methods as in ``report.METHODS``.
    """
    st = stage.settings
    h, f = st.history, st.future
    occ, disp = batch[setting.inputs], batch["ego_displacements"].float()
    device = disp.device
    current = occ[:, h - 1]
    ctr = constant_turn_rate_poses(batch["history_poses"].double(), f)
    others, plans = {}, {}
    if baselines:
        others = {
            "copy_paste": copy_paste_forecast(current, f),
            "warp_cv": warp_constant_velocity_forecast(current, disp[:, h - 2], f, stage.grid),
            "warp_ctr": warp_along_poses(current, ctr, stage.grid),
            "warp_object_cv": object_constant_velocity_forecast(
                occ[:, :h], batch["history_poses"].double(), f, stage.grid
            ),
        }
        plans = {
            "cv_traj": constant_velocity_trajectory(disp[:, : h - 1], f),
            "ctr_traj": ctr[..., :2].to(disp.dtype),
        }
        if headings is not None:
            headings.update(cv_traj=torch.zeros_like(ctr[..., 2]), ctr_traj=ctr[..., 2])
    # The command is derived from the GT future (as VAD / UniAD): "model, command from
    # history" withholds it, giving the model the command the same rule derives from the
    # constant-turn-rate extrapolation of the history (what the GT-derived one is worth).
    held = torch.as_tensor(command_indices(ctr[..., :2].cpu().numpy()), device=device)
    forecasts, trajs = {}, {}
    for name, command in (("model", batch["command"].long()), (HISTORY_COMMAND, held)):
        if stage.forecaster == "pose_warp":
            fc, poses = wmp.pose_forecast(stage, model, {**batch, "command": command}, setting)
            fc = fc if name == "model" else {name: fc["model"]}
            traj = poses[..., :2]
            checked = CHECKED if name == "model" else CHECKED_HISTORY_COMMAND
            trajs[checked], yaw = wmp.checked_plans(stage, model, batch, setting, poses)
            trajs[checked] = trajs[checked].to(disp.dtype)
            if headings is not None:
                headings[name], headings[checked] = poses[..., 2], yaw
            if name == "model" and getattr(model, "movers", None) == "learned":
                h = stage.settings.history
                fc[MODEL_MOVERS] = gt_pose_movers_row(
                    batch, setting.inputs, h, stage.grid, movers_of(model)
                )
        else:
            if tokens is None:
                tokens = stage.window_tokens(
                    batch, h, device, setting.inputs, setting.source, setting.tokenizer
                )
            fc, traj = token_forecast(stage, model, tokens, disp, command, setting)
            fc = {name: fc}
        forecasts.update(fc)
        trajs[name] = traj.to(disp.dtype)
    return {**forecasts, **others}, {**trajs, **plans}


def token_forecast(stage: Any, model, tokens, disp, command, setting):
    """Token-model forecast [B, S, X, Y, Z] and trajectory [B, S, 2] for one command."""
    h, f = stage.settings.history, stage.settings.future
    tok = stage._tokenizer_on(disp.device, setting.tokenizer)
    ro = model.rollout(tokens[:, :h], disp[:, : h - 1], command, steps=f)
    with autocast_off():  # the frozen tokenizer's codes in float32 on every device
        names = tok.cfg.codebook_names
        frames = [
            tok.decode(Tokens(ro.tokens[:, k], tok.cfg.codebook_sizes, names)) for k in range(f)
        ]
    return torch.stack(frames, dim=1), ro.trajectory
