"""The forecast's movers moved by the learned mover head (``stage.movers: learned``).

Each movable component of the current frame is tracked through the history
(:func:`renderworld.world.tracks.track_movers`); the model's
:class:`~renderworld.world.mover_head.MoverHead` predicts its displacement at every future step
from its track and the scene around it; the component is pasted there (whole voxels), the rest
of the frame unchanged and its old voxels free (:func:`renderworld.world.movers.paste_shifted`).
The planner's forecast-checked plan reads the same displacements
(:func:`renderworld.planning.scene.forecast_scene`). History only: nothing here reads the
future. Frames: the current ego frame (x forward, y left; metres).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from renderworld.constants import KEYFRAME_DT, GridSpec
from renderworld.world.mover_head import MoverHead, mover_inputs
from renderworld.world.movers import paste_shifted
from renderworld.world.tracks import MoverTrack, track_movers

__all__ = ["head_displacements", "learned_mover_frames", "predict_displacements"]


@torch.no_grad()
def head_displacements(
    head: MoverHead,
    current: np.ndarray,
    history_poses: np.ndarray,
    tracks: Sequence[MoverTrack],
    grid: GridSpec,
    steps: int,
    dt: float = KEYFRAME_DT,
) -> np.ndarray:
    """[N, steps, 2] float64 displacements (metres) of tracked movers by ``head``.

    Args:
        head: the mover head (its device is used).
        current: [X, Y, Z] labels of the current frame; history_poses: [H, 3] (x, y, yaw).
        tracks: the movers of that history; grid: the occupancy grid; steps: S; dt: seconds.
    """
    inp = mover_inputs(current, history_poses, tracks, grid, steps, dt)
    if not len(inp):
        return np.zeros((0, steps, 2))
    dev = next(head.parameters()).device
    was = head.training
    head.eval()
    try:
        with torch.autocast(device_type=dev.type, enabled=False):
            out = head(*(torch.from_numpy(a).to(dev) for a in (inp.feats, inp.patches, inp.base)))
    finally:
        head.train(was)
    return out.double().cpu().numpy()


def predict_displacements(
    head: MoverHead,
    history_occupancy: np.ndarray,
    history_poses: np.ndarray,
    grid: GridSpec,
    steps: int,
    dt: float = KEYFRAME_DT,
) -> tuple[list[MoverTrack], np.ndarray]:
    """(tracks, displacements [N, steps, 2] metres) of the movers of one history.

    Args:
        head: the mover head.
        history_occupancy: [H, X, Y, Z] labels, each frame in its own ego frame.
        history_poses: [H, 3] (x, y, yaw) of those frames in the current ego frame.
        grid: the occupancy grid; steps: S; dt: seconds.
    """
    occ = np.asarray(history_occupancy)
    tracks = track_movers(occ, history_poses, grid, dt)
    return tracks, head_displacements(head, occ[-1], history_poses, tracks, grid, steps, dt)


def learned_mover_frames(head: MoverHead, dt: float = KEYFRAME_DT):
    """A :data:`renderworld.world.movers.MoversFrames` moving movers by ``head``.

    The returned function maps (history [B, T, X, Y, Z], history poses [B, T, 3], steps S,
    grid) to [B, S, X, Y, Z] (frame k: the current frame with every mover where the head puts
    it k steps later, still in the current ego frame), the dtype and device of the history.
    """

    def frames(history_occupancy, history_poses, steps: int, grid: GridSpec) -> torch.Tensor:
        occ = torch.as_tensor(history_occupancy)
        occ_np = occ.detach().cpu().numpy()
        poses = torch.as_tensor(history_poses).detach().cpu().double().numpy()
        vs = np.asarray(grid.voxel_size[:2], dtype=np.float64)
        outs = []
        for i in range(occ_np.shape[0]):
            tracks, disp = predict_displacements(head, occ_np[i], poses[i], grid, steps, dt)
            shifts = np.rint(disp / vs).astype(np.int64)
            comps = [(tr.cls, tr.cells) for tr in tracks]
            outs.append(torch.from_numpy(paste_shifted(occ_np[i, -1], comps, shifts, steps)))
        return torch.stack(outs).to(occ.device)

    return frames
