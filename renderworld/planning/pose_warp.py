"""Planning with a pose-warp world model (``stage.forecaster=pose_warp``).

:class:`renderworld.world.pose.PoseWarpWorldModel` plans with the same steps as the
``world_model`` stage's evaluation
(:func:`renderworld.training.stages.world_model.pose_warp.pose_forecast`), without Hydra or the
stage: the planner *is* the model the stage scores.

1. History poses ``(x, y, yaw)`` [B, H, 3] in the current ego frame: positions from the request's
   displacements (``p[H-1] = 0``, ``p[j] = p[j+1] - d[j]``, in float64), yaws from
   ``ego_yaws``.
2. The pose head predicts the future poses [B, S, 3] from the history poses, the command and the
   current frame's bird's-eye view; the trajectory is their positions. A trajectory-only plan
   stops here: no encode, no token network, no decode.
3. Forecast: :func:`renderworld.world.forecast.pose_warp_forecast`, the one forecaster the
   stage scores too (the current frame - its movers moved first when the model's ``movers`` is
   ``object_cv`` - warped along the predicted poses, the aligned history and the warped frames
   encoded in one batch, the token network, the decode, the composition).

The aligned history depends on the current frame's pose, so a streaming session cannot reuse
encodes across frames: it keeps raw frames and runs these steps on each plan.
"""

from __future__ import annotations

import numpy as np
import torch

from renderworld.constants import OCC3D_GRID, GridSpec
from renderworld.tokenizer.tokens import Tokens
from renderworld.world.forecast import pose_warp_forecast

__all__ = [
    "check_tokens",
    "default_grid",
    "forecast_from_poses",
    "history_poses",
    "tokenizer_grid_shape",
]


def check_tokens(tokens, config, n: int) -> None:
    """Raise ValueError unless a tokenizer's ``encode`` output fits the world model.

    Args:
        tokens: what ``encode`` returned for n frames (a :class:`Tokens` [n, G, h, w]).
        config: the world model's config (codebook sizes, ``num_codebooks``, ``token_grid``).
        n: frames encoded.
    """
    if not isinstance(tokens, Tokens):
        raise ValueError(f"tokenizer: encode returned {type(tokens).__name__}, expected Tokens")
    if tuple(tokens.codebook_sizes) != config.codebook_sizes:
        raise ValueError(
            f"tokenizer: codebook sizes {tokens.codebook_sizes} do not match the world "
            f"model's {config.codebook_sizes}"
        )
    want = (n, config.num_codebooks, *config.token_grid)
    if tuple(tokens.indices.shape) != want:
        raise ValueError(
            f"tokenizer: token indices {tuple(tokens.indices.shape)} do not match the "
            f"world model's expected {want}"
        )


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


class _PlannerCodec:
    """The planner's :class:`~renderworld.world.forecast.FrameCodec`: one encode of the aligned
    history and the warped frames together; the milliseconds each call takes are summed."""

    def __init__(self, planner):
        self.planner = planner
        self.ms = {"encode": 0.0, "decode": 0.0}

    def encode(self, aligned: torch.Tensor, warped: torch.Tensor) -> tuple[torch.Tensor, ...]:
        b, h1, s = aligned.shape[0], aligned.shape[1], warped.shape[1]
        t0 = self.planner._sync()
        codes = self.planner.encode(torch.cat([aligned.flatten(0, 1), warped.flatten(0, 1)]))
        codes = codes.indices
        self.ms["encode"] += 1e3 * (self.planner._sync() - t0)
        hist_codes = codes[: b * h1].view(b, h1, *codes.shape[1:])
        return hist_codes, codes[b * h1 :].view(b, s, *codes.shape[1:])

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        t0 = self.planner._sync()
        out = self.planner._decode_codes(codes.flatten(0, 1))
        self.ms["decode"] += 1e3 * (self.planner._sync() - t0)
        return out.view(*codes.shape[:2], *out.shape[1:])


def forecast_from_poses(planner, occ, hist, poses, command) -> tuple[torch.Tensor, dict]:
    """Occupancy forecast [B, S, X, Y, Z] uint8 of a pose-warp model (step 3 of the module doc).

    Args:
        planner: the :class:`renderworld.planning.Planner` (its encode, decode and grid).
        occ: [B, H, X, Y, Z] uint8 history on the planner's device, each frame in its own ego
            frame.
        hist: [B, H, 3] float32 history poses; poses: [B, S, 3] predicted future poses.
        command: [B] int64.

    Returns:
        (forecast on the device, ``{"encode": ms, "world_model": ms, "decode": ms}``; the
        warp, the alignment and the token network count as ``world_model``).
    """
    codec = _PlannerCodec(planner)
    t0 = planner._sync()
    fc = pose_warp_forecast(
        planner.world_model, occ, hist, poses, command, planner.grid, codec,
        network_scope=planner._world_model_threads,
    )  # fmt: skip
    total = 1e3 * (planner._sync() - t0)
    rest = total - codec.ms["encode"] - codec.ms["decode"]
    return fc.forecast, {**codec.ms, "world_model": rest}
