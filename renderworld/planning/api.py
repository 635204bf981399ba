"""The planner API: occupancy history + current command -> 3 s trajectory and forecast.

Conventions (DESIGN.md §3, VAD per-step offsets, FACTS.md):

* ``PlanRequest.occupancy[i]`` is frame i of the history (oldest first, the last one is the
  current frame t), each in **its own** ego frame on the tokenizer's grid, Occ3D ids (17 free).
* ``PlanRequest.ego_displacements[i]`` = ``p[i + 1] - p[i]`` in metres, where ``p[k]`` is the
  ego origin (rear axle) of history frame k expressed in the **current** ego frame
  (x forward, y left). E.g. driving straight ahead at 10 m/s gives ``[5, 0]`` per row.
* ``PlanResult.trajectory[k]`` = predicted ``p[t + k + 1]``: positions of the future frames at
  +0.5 ... +3.0 s in the current ego frame (the cumulative sum of the predicted per-step
  displacements, the same convention), metres.
* The planner uses the last ``history_frames`` (5) frames when more are given, and holds the
  current command fixed through the rollout.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from renderworld.constants import COMMANDS, FREE_ID, HISTORY_FRAMES
from renderworld.tokenizer.tokens import Tokens
from renderworld.world.model import WorldModel

__all__ = ["PlanRequest", "PlanResult", "Planner"]


def _as_numpy(x, name: str) -> np.ndarray:
    if isinstance(x, np.ndarray):
        return x
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    raise TypeError(f"{name}: expected a numpy array or torch tensor, got {type(x).__name__}")


@dataclass(frozen=True)
class PlanRequest:
    """One planning query (validated on construction; see the module docstring for frames).

    Attributes:
        occupancy: [T, X, Y, Z] uint8 Occ3D ids (<= 17), T >= 5, oldest first.
        ego_displacements: [T-1, 2] float metres, current ego frame.
        command: ``"left"``, ``"right"`` or ``"straight"`` (the current command).
    """

    occupancy: np.ndarray
    ego_displacements: np.ndarray
    command: str

    def __post_init__(self) -> None:
        occ = _as_numpy(self.occupancy, "occupancy")
        if occ.dtype != np.uint8:
            raise ValueError(f"occupancy: expected dtype uint8, got {occ.dtype}")
        if occ.ndim != 4 or min(occ.shape) < 1:
            raise ValueError(f"occupancy: expected shape [T, X, Y, Z], got {occ.shape}")
        if occ.shape[0] < HISTORY_FRAMES:
            raise ValueError(
                f"occupancy: expected at least {HISTORY_FRAMES} history frames, got {occ.shape[0]}"
            )
        if int(occ.max()) > FREE_ID:
            raise ValueError(
                f"occupancy: expected class ids in [0, {FREE_ID}], got max {int(occ.max())}"
            )
        disp = _as_numpy(self.ego_displacements, "ego_displacements")
        if not np.issubdtype(disp.dtype, np.floating):
            raise ValueError(f"ego_displacements: expected a float dtype, got {disp.dtype}")
        if disp.shape != (occ.shape[0] - 1, 2):
            raise ValueError(
                f"ego_displacements: expected shape [T-1, 2] = [{occ.shape[0] - 1}, 2], "
                f"got {disp.shape}"
            )
        if not np.isfinite(disp).all():
            raise ValueError("ego_displacements: expected finite values, got NaN or inf")
        if not isinstance(self.command, str) or self.command not in COMMANDS:
            raise ValueError(f"command: expected one of {COMMANDS}, got {self.command!r}")


@dataclass(frozen=True)
class PlanResult:
    """Planner output.

    Attributes:
        trajectory: [S, 2] float32 metres, positions at +0.5 ... +S/2 s in the current ego frame.
        occupancy_forecast: [S, X, Y, Z] uint8, frame t+k+1 in its own (predicted) ego frame.
        timings: milliseconds: ``encode``, ``world_model``, ``decode``, ``total`` (for a
            batch: the whole batch's times) and ``batch_size``.
    """

    trajectory: np.ndarray
    occupancy_forecast: np.ndarray
    timings: dict = field(default_factory=dict)


class Planner:
    """Tokenizer + world model behind a small, validated API.

    Args:
        tokenizer: object with ``encode(occ [B, X, Y, Z] uint8) -> Tokens`` and
            ``decode(Tokens) -> [B, X, Y, Z] uint8`` (an ``nn.Module`` is moved to ``device``
            and set to eval mode).
        world_model: :class:`renderworld.world.WorldModel` whose codebooks and token grid match
            the tokenizer's.
        device: where both run.
    """

    def __init__(self, tokenizer, world_model: WorldModel, device: str | torch.device = "cpu"):
        for name in ("encode", "decode"):
            if not callable(getattr(tokenizer, name, None)):
                raise TypeError(f"tokenizer: expected an object with a callable .{name}()")
        if not isinstance(world_model, WorldModel):
            raise TypeError(f"world_model: expected WorldModel, got {type(world_model).__name__}")
        self.device = torch.device(device)
        self.tokenizer = tokenizer
        self.world_model = world_model.to(self.device).eval()
        if isinstance(tokenizer, torch.nn.Module):
            self.tokenizer = tokenizer.to(self.device).eval()
        self.config = world_model.config

    def _sync(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def plan(self, request: PlanRequest) -> PlanResult:
        """Plan for one request (see :meth:`plan_batch`)."""
        return self.plan_batch([request])[0]

    def plan_batch(self, requests) -> list[PlanResult]:
        """Plan for several requests in one batch (their grids must match).

        Inputs are never modified: the history is copied before use.

        Raises:
            TypeError: a request is not a :class:`PlanRequest`.
            ValueError: empty list, grids that differ, or tokens that do not fit the model.
        """
        reqs = list(requests)
        if not reqs:
            raise ValueError("requests: expected at least one PlanRequest, got none")
        for i, r in enumerate(reqs):
            if not isinstance(r, PlanRequest):
                raise TypeError(f"requests[{i}]: expected PlanRequest, got {type(r).__name__}")
        cfg = self.config
        h = cfg.history_frames
        grid = _as_numpy(reqs[0].occupancy, "occupancy").shape[1:]
        for i, r in enumerate(reqs):
            if r.occupancy.shape[0] < h:
                raise ValueError(
                    f"requests[{i}].occupancy: the world model needs {h} history frames, "
                    f"got {r.occupancy.shape[0]}"
                )
            if _as_numpy(r.occupancy, "occupancy").shape[1:] != grid:
                raise ValueError(
                    f"requests[{i}].occupancy: expected grid {grid} like requests[0], "
                    f"got {r.occupancy.shape[1:]}"
                )
        # np.stack copies: the requests' arrays are never written to.
        occ = np.stack([_as_numpy(r.occupancy, "occupancy")[-h:] for r in reqs])
        disp = np.stack(
            [_as_numpy(r.ego_displacements, "ego_displacements")[-(h - 1) :] for r in reqs]
        ).astype(np.float32)
        b = len(reqs)
        cmd = torch.tensor([COMMANDS.index(r.command) for r in reqs], device=self.device)

        with torch.inference_mode():
            t0 = self._sync()
            occ_t = torch.from_numpy(occ).to(self.device).reshape(b * h, *grid)
            tokens = self.tokenizer.encode(occ_t)
            self._check_tokens(tokens, b * h)
            t1 = self._sync()
            idx = tokens.indices.reshape(b, h, *tokens.indices.shape[1:])
            out = self.world_model.rollout(
                idx, torch.from_numpy(disp).to(self.device), cmd, steps=cfg.future_frames
            )
            t2 = self._sync()
            s = cfg.future_frames
            fut = Tokens(
                out.tokens.reshape(b * s, *out.tokens.shape[2:]),
                tokens.codebook_sizes,
                tokens.codebook_names,
            )
            dec = self.tokenizer.decode(fut)
            t3 = self._sync()
        if not isinstance(dec, torch.Tensor) or tuple(dec.shape) != (b * s, *grid):
            raise ValueError(
                f"tokenizer: decode returned {getattr(dec, 'shape', type(dec))}, "
                f"expected [{b * s}, {', '.join(map(str, grid))}]"
            )
        forecast = dec.to(torch.uint8).reshape(b, s, *grid).cpu().numpy()
        traj = out.trajectory.float().cpu().numpy()
        timings = {
            "encode": 1e3 * (t1 - t0),
            "world_model": 1e3 * (t2 - t1),
            "decode": 1e3 * (t3 - t2),
            "total": 1e3 * (t3 - t0),
            "batch_size": b,
        }
        return [PlanResult(traj[i], forecast[i], dict(timings)) for i in range(b)]

    def _check_tokens(self, tokens, n: int) -> None:
        cfg = self.config
        if not isinstance(tokens, Tokens):
            raise ValueError(f"tokenizer: encode returned {type(tokens).__name__}, expected Tokens")
        if tuple(tokens.codebook_sizes) != cfg.codebook_sizes:
            raise ValueError(
                f"tokenizer: codebook sizes {tokens.codebook_sizes} do not match the world "
                f"model's {cfg.codebook_sizes}"
            )
        want = (n, cfg.num_codebooks, *cfg.token_grid)
        if tuple(tokens.indices.shape) != want:
            raise ValueError(
                f"tokenizer: token indices {tuple(tokens.indices.shape)} do not match the "
                f"world model's expected {want}"
            )
