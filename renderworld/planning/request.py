"""Planner requests and results, and the checks every way into the planner shares.

Conventions (docs/conventions.md#ego-motion-and-the-command, VAD per-step offsets):

* ``PlanRequest.occupancy[i]`` is frame i of the history (oldest first, the last one is the
  current frame t), each in **its own** ego frame on the tokenizer's grid, Occ3D ids (17 free).
* ``PlanRequest.ego_displacements[i]`` = ``p[i + 1] - p[i]`` in metres, where ``p[k]`` is the
  ego origin (rear axle) of history frame k expressed in the **current** ego frame
  (x forward, y left). E.g. driving straight ahead at 10 m/s gives ``[5, 0]`` per row.
* ``PlanRequest.ego_yaws[i]`` = yaw (radians, counter-clockwise) of history frame i's ego frame in
  the **current** ego frame, so the last one is 0. The token world model does not read it; the
  pose-warp world model needs it (it rotates the history into the current frame and
  extrapolates the turn rate). :func:`renderworld.world.ego.frame_poses_from_poses` gives
  ``(x, y, yaw)`` rows whose differences are the displacements and whose last column is this.
* ``PlanResult.trajectory[k]`` = predicted ``p[t + k + 1]``: positions of the future frames at
  +0.5 ... +3.0 s in the current ego frame (the cumulative sum of the predicted per-step
  displacements, the same convention), metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from renderworld.constants import COMMANDS, FREE_ID, HISTORY_FRAMES, KEYFRAME_DT

__all__ = [
    "MAX_STEP_DISPLACEMENT_M",
    "PlanRequest",
    "PlanResult",
    "check_command",
    "check_displacements",
    "check_occupancy",
    "check_yaws",
]

#: Largest accepted length (metres) of one history step ``d[i]`` (one keyframe interval,
#: 0.5 s): 50 m per 0.5 s is 100 m/s = 360 km/h, beyond any road vehicle; a longer step is a
#: unit or frame error (e.g. global coordinates or millimetres), not driving.
MAX_STEP_DISPLACEMENT_M: float = 50.0

#: Slack (radians) on the yaw checks: float32 round-off of poses computed elsewhere.
YAW_TOLERANCE: float = 1e-6


def as_numpy(x, name: str) -> np.ndarray:
    """A numpy view of ``x`` (numpy array or torch tensor); TypeError naming ``name`` else."""
    if isinstance(x, np.ndarray):
        return x
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    raise TypeError(f"{name}: expected a numpy array or torch tensor, got {type(x).__name__}")


def check_occupancy(occ, name: str = "occupancy", min_frames: int = HISTORY_FRAMES) -> np.ndarray:
    """Validate an occupancy history [T, X, Y, Z] uint8 Occ3D ids, T >= ``min_frames``.

    Returns:
        The array (numpy view, not copied).
    """
    occ = as_numpy(occ, name)
    if occ.dtype != np.uint8:
        raise ValueError(f"{name}: expected dtype uint8, got {occ.dtype}")
    if occ.ndim != 4 or min(occ.shape) < 1:
        raise ValueError(f"{name}: expected shape [T, X, Y, Z], got {occ.shape}")
    if occ.shape[0] < min_frames:
        raise ValueError(
            f"{name}: expected at least {min_frames} history frames, got {occ.shape[0]}"
        )
    if int(occ.max()) > FREE_ID:
        raise ValueError(f"{name}: expected class ids in [0, {FREE_ID}], got max {int(occ.max())}")
    return occ


def check_displacements(disp, rows: int, name: str = "ego_displacements") -> np.ndarray:
    """Validate per-step ego displacements [rows, 2] metres (finite, physically possible).

    Each row's length must be at most :data:`MAX_STEP_DISPLACEMENT_M` (50 m per 0.5 s).

    Returns:
        The array (numpy view, not copied).
    """
    disp = as_numpy(disp, name)
    if not np.issubdtype(disp.dtype, np.floating):
        raise ValueError(f"{name}: expected a float dtype, got {disp.dtype}")
    if disp.shape != (rows, 2):
        raise ValueError(f"{name}: expected shape [T-1, 2] = [{rows}, 2], got {disp.shape}")
    if not np.isfinite(disp).all():
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    if rows:
        step = np.hypot(disp[:, 0].astype(np.float64), disp[:, 1].astype(np.float64))
        worst = int(step.argmax())
        if step[worst] > MAX_STEP_DISPLACEMENT_M:
            raise ValueError(
                f"{name}: expected steps of at most {MAX_STEP_DISPLACEMENT_M:g} m per "
                f"{KEYFRAME_DT:g} s ({MAX_STEP_DISPLACEMENT_M / KEYFRAME_DT:g} m/s), got "
                f"{step[worst]:.6g} m at row {worst}"
            )
    return disp


def check_yaws(yaws, rows: int, name: str = "ego_yaws") -> np.ndarray:
    """Validate history yaws [rows] radians in the current ego frame (finite, in [-pi, pi],
    the last one 0: the current frame's own yaw).

    Returns:
        The array (numpy view, not copied).
    """
    yaws = as_numpy(yaws, name)
    if not np.issubdtype(yaws.dtype, np.floating):
        raise ValueError(f"{name}: expected a float dtype, got {yaws.dtype}")
    if yaws.shape != (rows,):
        raise ValueError(f"{name}: expected shape [T] = [{rows}], got {yaws.shape}")
    if not np.isfinite(yaws).all():
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    worst = float(np.abs(yaws).max())
    if worst > np.pi + YAW_TOLERANCE:
        raise ValueError(f"{name}: expected radians in [-pi, pi], got |yaw| = {worst:.6g}")
    if abs(float(yaws[-1])) > YAW_TOLERANCE:
        raise ValueError(
            f"{name}: expected 0 for the current frame (last row; yaws are in the current ego "
            f"frame), got {float(yaws[-1]):.6g}"
        )
    return yaws


def check_command(command) -> str:
    """Validate a driving command (one of ``COMMANDS``)."""
    if not isinstance(command, str) or command not in COMMANDS:
        raise ValueError(f"command: expected one of {COMMANDS}, got {command!r}")
    return command


@dataclass(frozen=True)
class PlanRequest:
    """One planning query (validated on construction; see the module docstring for frames).

    Attributes:
        occupancy: [T, X, Y, Z] uint8 Occ3D ids (<= 17), T >= 5, oldest first.
        ego_displacements: [T-1, 2] float metres, current ego frame; each step at most
            :data:`MAX_STEP_DISPLACEMENT_M` = 50 m long (360 km/h over 0.5 s), finite.
        command: ``"left"``, ``"right"`` or ``"straight"`` (the current command).
        ego_yaws: None, or [T] float radians, yaw of each history frame in the current ego
            frame (last 0); needed by pose-warp world models, ignored by token world models.
    """

    occupancy: np.ndarray
    ego_displacements: np.ndarray
    command: str
    ego_yaws: np.ndarray | None = None

    def __post_init__(self) -> None:
        occ = check_occupancy(self.occupancy)
        check_displacements(self.ego_displacements, occ.shape[0] - 1)
        check_command(self.command)
        if self.ego_yaws is not None:
            check_yaws(self.ego_yaws, occ.shape[0])


@dataclass(frozen=True)
class PlanResult:
    """Planner output.

    Attributes:
        trajectory: [S, 2] float32 metres, positions at +0.5 ... +S/2 s in the current ego frame.
        occupancy_forecast: [S, X, Y, Z] uint8, frame t+k+1 in its own (predicted) ego frame;
            None for a trajectory-only plan (``forecast=False``).
        timings: milliseconds: ``encode``, ``world_model``, ``decode``, ``total`` (for a
            batch: the whole batch's times) and ``batch_size``.
        yaws: [S] float32 radians, heading of each predicted future ego frame in the current
            ego frame (the frame ``occupancy_forecast[k]`` is in) for a pose-aware world model;
            None for a token world model, whose frames follow the travel direction.
        raw_trajectory: [S, 2] float32 metres, the world model's own plan, for a checked plan
            (``check=True``; ``trajectory`` is then the chosen candidate's); else None.
        candidates: every candidate of a checked plan and its scores
            (:class:`renderworld.planning.check.CandidateScores`); else None.
    """

    trajectory: np.ndarray
    occupancy_forecast: np.ndarray | None
    timings: dict = field(default_factory=dict)
    yaws: np.ndarray | None = None
    raw_trajectory: np.ndarray | None = None
    candidates: object | None = None


def stack_requests(requests, history_frames: int) -> tuple[np.ndarray, np.ndarray, list]:
    """Validate requests of one batch and stack their last ``history_frames`` frames.

    Args:
        requests: :class:`PlanRequest` objects sharing one grid.
        history_frames: H, the frames the world model reads.

    Returns:
        occupancy [B, H, X, Y, Z] uint8 and displacements [B, H-1, 2] (copies: the requests'
        arrays are never written to), and the requests as a list.

    Raises:
        TypeError: a request is not a :class:`PlanRequest`.
        ValueError: no request, too few frames, or grids that differ.
    """
    reqs = list(requests)
    if not reqs:
        raise ValueError("requests: expected at least one PlanRequest, got none")
    for i, r in enumerate(reqs):
        if not isinstance(r, PlanRequest):
            raise TypeError(f"requests[{i}]: expected PlanRequest, got {type(r).__name__}")
    h = history_frames
    grid = as_numpy(reqs[0].occupancy, "occupancy").shape[1:]
    for i, r in enumerate(reqs):
        if r.occupancy.shape[0] < h:
            raise ValueError(
                f"requests[{i}].occupancy: the world model needs {h} history frames, "
                f"got {r.occupancy.shape[0]}"
            )
        if as_numpy(r.occupancy, "occupancy").shape[1:] != grid:
            raise ValueError(
                f"requests[{i}].occupancy: expected grid {grid} like requests[0], "
                f"got {r.occupancy.shape[1:]}"
            )
    occ = np.stack([as_numpy(r.occupancy, "occupancy")[-h:] for r in reqs])
    disp = np.stack([as_numpy(r.ego_displacements, "ego_displacements")[-(h - 1) :] for r in reqs])
    return occ, disp, reqs
