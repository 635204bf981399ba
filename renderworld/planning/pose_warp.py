"""Planning with a pose-warp world model (``stage.forecaster=pose_warp``).

:class:`renderworld.world.pose.PoseWarpWorldModel` plans with the same steps as the
``world_model`` stage's evaluation
(:func:`renderworld.training.stages.world_model_pose.pose_forecast`), without Hydra or the
stage: the planner *is* the model the stage scores.

1. History poses ``(x, y, yaw)`` [B, H, 3] in the current ego frame: positions from the request's
   displacements (``p[H-1] = 0``, ``p[j] = p[j+1] - d[j]``, in float64), yaws from
   ``ego_yaws``.
2. The pose head predicts the future poses [B, S, 3] from the history poses, the command and the
   current frame's bird's-eye view; the trajectory is their positions. A trajectory-only plan
   stops here: no encode, no token network, no decode.
3. Forecast: the current frame warped along the predicted poses; the history frames t-H+1..t-1
   brought into the current frame (:func:`renderworld.world.pose.align_history`); both encoded
   (H-1+S frames in one batch); the token network scores the future codes; their argmax is
   decoded; the forecast takes the warp where its source lies on the current grid and, elsewhere,
   the decoded classes the current frame holds (free otherwise).

The aligned history depends on the current frame's pose, so a streaming session cannot reuse
encodes across frames: it keeps raw frames and runs these steps on each plan.
"""

from __future__ import annotations

import numpy as np
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES, OCC3D_GRID, GridSpec
from renderworld.world.baselines import warp_along_poses
from renderworld.world.pose import align_history

__all__ = ["default_grid", "forecast_from_poses", "history_poses", "tokenizer_grid_shape"]


def tokenizer_grid_shape(tokenizer) -> tuple[int, int, int] | None:
    """The tokenizer's occupancy grid [X, Y, Z] (``cfg.grid_shape`` or ``config.grid_shape``),
    or None when it names none."""
    for attr in ("cfg", "config"):
        shape = getattr(getattr(tokenizer, attr, None), "grid_shape", None)
        if shape is not None:
            return tuple(int(v) for v in shape)
    return None


def default_grid(shape) -> GridSpec:
    """The Occ3D-range grid (every named grid of :data:`renderworld.constants.GRIDS`) of a
    volume shape [X, Y, Z]."""
    dims = tuple(int(s) for s in shape)
    return GridSpec("x".join(map(str, dims)), OCC3D_GRID.range_min, OCC3D_GRID.range_max, dims)


def history_poses(displacements: np.ndarray, yaws: np.ndarray) -> torch.Tensor:
    """History poses from per-step displacements and yaws.

    Args:
        displacements: [B, H-1, 2] metres, ``d[i] = p[i+1] - p[i]``, current ego frame.
        yaws: [B, H] radians, current ego frame (last 0).

    Returns:
        [B, H, 3] float32 (x, y, yaw) of frames t-H+1..t in the current ego frame (the positions
        summed in float64 from the last frame backwards: exact for displacements that are float64
        differences of float32 positions).
    """
    d = np.asarray(displacements, dtype=np.float64)
    b, n = d.shape[:2]
    pos = np.zeros((b, n + 1, 2), dtype=np.float64)
    pos[:, :-1] = -np.cumsum(d[:, ::-1], axis=1)[:, ::-1]
    out = np.concatenate([pos, np.asarray(yaws, dtype=np.float64)[..., None]], axis=-1)
    return torch.from_numpy(out.astype(np.float32))


def _bev_grid(grid: GridSpec) -> GridSpec:
    """The grid with one z level (the inside-the-grid mask is the same at every z)."""
    lo, hi = list(grid.range_min), list(grid.range_max)
    return GridSpec(f"{grid.name}-bev", tuple(lo), tuple(hi), (grid.shape[0], grid.shape[1], 1))


def forecast_from_poses(planner, occ, hist, poses, command) -> tuple[torch.Tensor, dict]:
    """Occupancy forecast [B, S, X, Y, Z] uint8 of a pose-warp model (step 3 of the module doc).

    Args:
        planner: the :class:`renderworld.planning.Planner` (its encode, decode and grid).
        occ: [B, H, X, Y, Z] uint8 history on the planner's device, each frame in its own ego
            frame.
        hist: [B, H, 3] float32 history poses; poses: [B, S, 3] predicted future poses.
        command: [B] int64.

    Returns:
        (forecast on the device, ``{"encode": ms, "world_model": ms, "decode": ms}``).
    """
    model, grid = planner.world_model, planner.grid
    b, h = occ.shape[:2]
    s = poses.shape[1]
    t0 = planner._sync()
    current = occ[:, h - 1]
    warped = warp_along_poses(current, poses.double(), grid)  # [B, S, X, Y, Z]
    ones = torch.ones(current.shape[:3], dtype=torch.uint8, device=occ.device)
    inside = warp_along_poses(ones[..., None], poses.double(), _bev_grid(grid), fill=0)[..., 0]
    aligned = align_history(occ[:, : h - 1], hist[:, : h - 1], grid)
    t1 = planner._sync()
    frames = torch.cat([aligned.flatten(0, 1), warped.flatten(0, 1)])
    codes = planner.encode(frames).indices
    t2 = planner._sync()
    hist_codes = codes[: b * (h - 1)].view(b, h - 1, *codes.shape[1:])
    base_codes = codes[b * (h - 1) :].view(b, s, *codes.shape[1:])
    seq = torch.cat([hist_codes, base_codes], dim=1)
    seq_poses = torch.cat([hist[:, : h - 1], poses], dim=1)
    with planner._world_model_threads():
        logits = model(seq, seq_poses, command)
    future = torch.stack([lg.argmax(dim=2) for lg in logits], dim=2)  # [B, S, G, h, w]
    t3 = planner._sync()
    net = planner._decode_codes(future.flatten(0, 1)).view(warped.shape).to(warped.dtype)
    # Newly revealed space continues what the current frame shows: decoded classes the current
    # frame does not hold there are left free.
    seen = torch.zeros(b, NUM_OCC3D_CLASSES, dtype=torch.bool, device=occ.device)
    seen.scatter_(1, current.flatten(1).long(), True)
    keep = seen.gather(1, net.flatten(1).long()).view(net.shape)
    fill = torch.where(keep, net, torch.full_like(net, FREE_ID))
    forecast = torch.where(inside[..., None].bool(), warped, fill)
    t4 = planner._sync()
    ms = {"encode": 1e3 * (t2 - t1), "world_model": 1e3 * (t1 - t0 + t3 - t2),
          "decode": 1e3 * (t4 - t3)}  # fmt: skip
    return forecast, ms
