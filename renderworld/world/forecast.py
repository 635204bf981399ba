"""The pose-warp forecast: one home for the ``world_model`` stage's evaluation and the planner.

:class:`renderworld.world.pose.PoseWarpWorldModel` forecasts in four steps, given the future
poses its pose head predicted:

1. **Warp** (:func:`warp_current`): the current frame carried into each future ego frame along
   the poses. With ``movers="object_cv"`` every movable bird's-eye-view component of the
   current frame first moves at its own velocity, measured against frame t-2 brought into the
   current frame (:func:`renderworld.world.movers.object_cv_frames`; parked objects, unmatched
   objects and new ones stay put in the world); with ``"learned"`` each one moves where the
   model's mover head puts it (:mod:`renderworld.world.learned_movers`); with ``"static"``
   nothing moves.
2. **Encode**: the history frames t-H+1..t-1 brought into the current ego frame
   (:func:`renderworld.world.pose.align_history`) and the warped frames, by the caller's
   :class:`FrameCodec` (the stage caches codes; the planner encodes one batch).
3. **Token network**: scores the future codes; their argmax is decoded by the codec.
4. **Compose** (:func:`compose_forecast`): the warp wherever its source lies on the current
   grid; elsewhere (newly revealed space) the decoded static classes the current frame holds,
   free otherwise. A token decoder's stray classes would each add a present class at IoU ~0 to
   the mIoU, and its movers there are guesses that cost more than they place
   (docs/world_model.md). So no road user enters the grid through newly revealed space; those
   already on it leave it.

The forecast reads the history occupancy, the history poses and the command, nothing else.
The command is the caller's: the evaluation's standard command is derived from the ground-truth
future (the lateral offset of the 3 s position, as VAD / UniAD / OccWorld do), so the ``model``
rows read the future through it; the evaluation row "model, command from history" passes the
command the same rule derives from the history and reads no future. Poses are (x, y, yaw) in
the current ego frame (x forward, y left; metres, radians).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES, GridSpec
from renderworld.world.baselines import warp_along_poses
from renderworld.world.learned_movers import learned_mover_frames
from renderworld.world.movers import (
    MOVERS,
    MoversFrames,
    movable_mask,
    object_cv_frames,
    warp_frames_along_poses,
)
from renderworld.world.pose import align_history

__all__ = [
    "MOVERS",
    "FrameCodec",
    "PoseWarpForecast",
    "bev_grid",
    "check_movers",
    "compose_forecast",
    "inside_mask",
    "movers_of",
    "pose_warp_forecast",
    "warp_current",
]


class FrameCodec(Protocol):
    """How a caller turns occupancy frames into codes and back (its tokenizer, its cache)."""

    def encode(self, aligned: torch.Tensor, warped: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Codes of the aligned history [B, H-1, X, Y, Z] and the warped frames [B, S, X, Y, Z]:
        ([B, H-1, G, h, w], [B, S, G, h, w]) int64."""

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """Labels [B, S, X, Y, Z] of codes [B, S, G, h, w]."""


@dataclass
class PoseWarpForecast:
    """A pose-warp forecast [B, S, X, Y, Z] (labels, each frame in its own future ego frame).

    Attributes:
        forecast: the model's forecast (step 4 of the module doc).
        warp: the warp alone (``model, warp only``).
        net: the token network's decoded forecast alone (``model, tokens only``).
    """

    forecast: torch.Tensor
    warp: torch.Tensor
    net: torch.Tensor


def check_movers(movers: str, where: str = "movers") -> str:
    """``movers`` if it is one of :data:`MOVERS`, else a ValueError naming ``where``."""
    if movers not in MOVERS:
        raise ValueError(f"{where}: expected one of {MOVERS}, got {movers!r}")
    return movers


def bev_grid(grid: GridSpec) -> GridSpec:
    """The grid with one z level (the inside-the-grid mask is the same at every z)."""
    lo, hi = list(grid.range_min), list(grid.range_max)
    return GridSpec(f"{grid.name}-bev", tuple(lo), tuple(hi), (grid.shape[0], grid.shape[1], 1))


def inside_mask(poses: torch.Tensor, grid: GridSpec, device: torch.device) -> torch.Tensor:
    """[B, S, X, Y] bool: cells of future frame k whose source lies on the current grid.

    Args:
        poses: [B, S, 3] future poses in the current ego frame.
        grid: the occupancy grid.
        device: where the mask lives.
    """
    b = poses.shape[0]
    ones = torch.ones((b, grid.shape[0], grid.shape[1], 1), dtype=torch.uint8, device=device)
    return warp_along_poses(ones, poses.double(), bev_grid(grid), fill=0)[..., 0].bool()


def movers_of(model) -> str | MoversFrames:
    """How ``model``'s forecast moves others: ``"static"``, or the function that moves them
    (:func:`~renderworld.world.movers.object_cv_frames`, or its mover head's frames).

    Raises:
        ValueError: ``movers="learned"`` on a model without a mover head.
    """
    movers = check_movers(getattr(model, "movers", "static"))
    if movers == "static":
        return "static"
    if movers == "object_cv":
        return object_cv_frames
    head = getattr(model, "mover_head", None)
    if head is None:
        raise ValueError("movers: 'learned' needs a model with a mover head, this one has none")
    return learned_mover_frames(head)


def warp_current(
    history: torch.Tensor,
    history_poses: torch.Tensor,
    poses: torch.Tensor,
    grid: GridSpec,
    movers: str | MoversFrames = "static",
) -> torch.Tensor:
    """The current frame warped along future poses (step 1 of the module doc).

    Args:
        history: [B, H, X, Y, Z] labels, each frame in its own ego frame (the last: current).
        history_poses: [B, H, 3] poses of those frames in the current ego frame (read only
            when the movers move).
        poses: [B, S, 3] future poses in the current ego frame.
        grid: the occupancy grid.
        movers: one of :data:`MOVERS` but ``"learned"``, or a function moving the movers
            (:func:`movers_of`).

    Returns:
        [B, S, X, Y, Z], the dtype of ``history``.
    """
    if not callable(movers):
        if check_movers(movers) == "learned":
            raise ValueError("movers: 'learned' needs the model's mover frames (movers_of)")
        if movers == "static":
            return warp_along_poses(history[:, -1], poses.double(), grid)
        movers = object_cv_frames
    moved = movers(history, history_poses.double(), poses.shape[1], grid)
    return warp_frames_along_poses(moved, poses.double(), grid)


def compose_forecast(
    current: torch.Tensor, warped: torch.Tensor, inside: torch.Tensor, net: torch.Tensor
) -> torch.Tensor:
    """Step 4 of the module doc.

    Args:
        current: [B, X, Y, Z] labels of the current frame.
        warped: [B, S, X, Y, Z] the warp; inside: [B, S, X, Y] bool (:func:`inside_mask`).
        net: [B, S, X, Y, Z] decoded token forecast (any integer dtype; cast to ``warped``'s).

    Returns:
        [B, S, X, Y, Z], the dtype of ``warped``.
    """
    b = current.shape[0]
    net = net.to(warped.dtype)
    seen = torch.zeros(b, NUM_OCC3D_CLASSES, dtype=torch.bool, device=current.device)
    seen.scatter_(1, current.flatten(1).long(), True)
    keep = seen.gather(1, net.flatten(1).long()).view(net.shape) & ~movable_mask(net)
    fill = torch.where(keep, net, torch.full_like(net, FREE_ID))
    return torch.where(inside[..., None], warped, fill)


def pose_warp_forecast(
    model: torch.nn.Module,
    history: torch.Tensor,
    history_poses: torch.Tensor,
    poses: torch.Tensor,
    command: torch.Tensor,
    grid: GridSpec,
    codec: FrameCodec,
    network_scope: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext,
) -> PoseWarpForecast:
    """The forecast of a :class:`~renderworld.world.pose.PoseWarpWorldModel` along its poses.

    Args:
        model: the pose-warp world model (its ``movers`` says how others move).
        history: [B, H, X, Y, Z] labels of frames t-H+1..t, each in its own ego frame.
        history_poses: [B, H, 3] poses of those frames in the current ego frame (float32 or
            float64; the token network reads them in the dtype of ``poses``).
        poses: [B, S, 3] the predicted future poses.
        command: [B] int64.
        grid: the occupancy grid.
        codec: encodes the aligned history and the warped frames, decodes the forecast codes.
        network_scope: a context the token network runs in (the planner's thread count).

    Returns:
        :class:`PoseWarpForecast`.
    """
    h = history.shape[1]
    current = history[:, h - 1]
    warped = warp_current(history, history_poses, poses, grid, movers_of(model))
    inside = inside_mask(poses, grid, history.device)
    aligned = align_history(history[:, : h - 1], history_poses[:, : h - 1], grid)
    hist_codes, base_codes = codec.encode(aligned, warped)
    seq = torch.cat([hist_codes, base_codes], dim=1)
    seq_poses = torch.cat([history_poses[:, : h - 1].to(poses.dtype), poses], dim=1)
    with network_scope():
        logits = model(seq, seq_poses, command)
    codes = torch.stack([lg.argmax(dim=2) for lg in logits], dim=2)  # [B, S, G, h, w]
    net = codec.decode(codes).to(warped.dtype)
    return PoseWarpForecast(compose_forecast(current, warped, inside, net), warped, net)
