"""The references of the ``world_model`` evaluation: forecasts that read the future.

They are reported beside the model and the baselines, labelled "(ref.)", and never compete
(docs/protocol.md#baselines-and-references). Each reads no model, so the evaluation scores them
once per validation set (``evaluation.MODEL_FREE_METHODS``):

* ``warp_gt_pose`` - the current frame warped along the ground-truth future poses
  ``future_poses``: an upper bound for a static world.
* ``warp_gt_object_cv`` - the current frame with its movers moved by the object-CV rule
  (history only, :func:`renderworld.world.movers.object_cv_frames`) warped along the same
  poses: the pose-warp design's forecast with perfect ego poses
  (:func:`renderworld.world.movers.gt_pose_movers_reference`; another movers rule, e.g. a
  learned one, gives its own row through :func:`gt_pose_movers_row`).
* ``warp_gt_movers`` - the GT-pose warp of the current frame without its movers, the scored
  target's future movers pasted in: an upper bound for a forecast that moves objects.

Frames: every forecast frame k lies in its own future ego frame k, like the scored target.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from renderworld.constants import GridSpec
from renderworld.world.baselines import warp_along_poses
from renderworld.world.movers import (
    MoversFrames,
    gt_movers_reference,
    gt_pose_movers_reference,
    object_cv_frames,
)

__all__ = ["gt_pose_movers_row", "reference_forecasts"]


def gt_pose_movers_row(
    batch: Mapping,
    inputs: str,
    history: int,
    grid: GridSpec,
    movers_frames: MoversFrames = object_cv_frames,
) -> torch.Tensor:
    """A "GT-pose + movers" reference of a batch: [B, S, X, Y, Z], the dtype of the inputs.

    Args:
        batch: a collated batch of ``WorldModelWindows`` (``history_poses``, ``future_poses``
            and the occupancy ``inputs`` are read).
        inputs: batch key of the setting's occupancy (``"occ"`` or ``"occ_target"``).
        history: H, history frames of a window (the last is the current frame).
        grid: the occupancy grid.
        movers_frames: how the current frame's movers move (history only); see
            :data:`renderworld.world.movers.MoversFrames`.
    """
    return gt_pose_movers_reference(
        batch[inputs][:, :history], batch["history_poses"], batch["future_poses"], grid,
        movers_frames,
    )  # fmt: skip


def reference_forecasts(
    batch: Mapping, inputs: str, history: int, grid: GridSpec
) -> dict[str, torch.Tensor]:
    """Every reference of the module docstring for one setting's inputs.

    Args:
        batch: a collated batch of ``WorldModelWindows``; ``occ_target`` (else ``occ``) is the
            scored target whose future movers ``warp_gt_movers`` pastes in.
        inputs: batch key of the setting's history occupancy (its current frame is warped).
        history: H, history frames of a window.
        grid: the occupancy grid.

    Returns:
        ``{method: [B, S, X, Y, Z]}`` (methods as in ``report.METHODS``), the dtype of the inputs.
    """
    current = batch[inputs][:, history - 1]
    future = batch.get("occ_target", batch["occ"])[:, history:]
    poses = batch["future_poses"]
    return {
        "warp_gt_pose": warp_along_poses(current, poses, grid),
        "warp_gt_object_cv": gt_pose_movers_row(batch, inputs, history, grid),
        "warp_gt_movers": gt_movers_reference(current, future, poses, grid),
    }
