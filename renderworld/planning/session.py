"""Streaming planning: a session keeps the encoded history, so a new frame costs one encode.

In a car's loop the planner sees one new occupancy frame per keyframe (0.5 s). Re-planning
from a :class:`PlanRequest` would encode all five history frames again; a session encodes
each frame once, keeps the last ``history_frames`` frames' tokens, and rolls out from them::

    session = PlannerSession(planner)
    for occ_t, disp_t, cmd_t in stream:            # occ_t [X, Y, Z] uint8, own ego frame
        session.push(occ_t)                         # one encode
        if session.ready:
            result = session.plan(disp_t, cmd_t)    # disp_t [>= 4, 2], current ego frame

The tokens of a frame do not depend on the other frames (the tokenizer encodes each frame by
itself), so :meth:`PlannerSession.plan` equals :meth:`Planner.plan` on the same last five
frames. The displacements are passed with every plan because they are expressed in the
**current** ego frame, which changes with every frame (only the occupancy is reusable).

With a pose-warp world model (``planner.kind == "pose_warp"``) the session keeps the raw frames
instead (``push`` encodes nothing): that model encodes the history *brought into the current
frame*, which changes with every frame, so there is no per-frame encode to reuse; ``plan`` then
also takes the history yaws (``ego_yaws``, current ego frame) and runs exactly
:meth:`Planner.plan`'s steps on the kept frames.
"""

from __future__ import annotations

from collections import deque

import numpy as np
import torch

from renderworld.constants import KEYFRAME_DT
from renderworld.planning.api import Planner
from renderworld.planning.request import (
    PlanResult,
    as_numpy,
    check_command,
    check_displacements,
    check_occupancy,
    check_yaws,
)

__all__ = ["PlannerSession"]


class PlannerSession:
    """Encoded history of one vehicle's stream of occupancy frames.

    Args:
        planner: the :class:`Planner` that encodes and plans.
    """

    def __init__(self, planner: Planner):
        if not isinstance(planner, Planner):
            raise TypeError(f"planner: expected Planner, got {type(planner).__name__}")
        self.planner = planner
        self.history_frames = planner.config.history_frames
        self._tokens: deque[torch.Tensor] = deque(maxlen=self.history_frames)
        self._grid: tuple[int, ...] | None = None
        self._last_encode_ms = 0.0
        self.frames_seen = 0
        self._cruise = 0.0  # the fastest the ego drove since the last reset, m/s
        self._previous: tuple[int, np.ndarray] | None = None  # (frames seen, last checked plan)

    @property
    def ready(self) -> bool:
        """Whether ``history_frames`` frames have been pushed (a plan is possible)."""
        return len(self._tokens) == self.history_frames

    def reset(self) -> None:
        """Forget the history (e.g. after a gap in the stream)."""
        self._tokens.clear()
        self._grid = None
        self._last_encode_ms = 0.0
        self.frames_seen = 0
        self._cruise = 0.0
        self._previous = None

    def push(self, occupancy) -> float:
        """Encode the newest frame and append it to the history (the oldest one drops out).

        Args:
            occupancy: [X, Y, Z] uint8 Occ3D ids of the new current frame, in its own ego
                frame, on the tokenizer's grid (the same grid as earlier frames).

        Returns:
            The encode time in milliseconds.
        """
        occ = check_occupancy(as_numpy(occupancy, "occupancy")[None], "occupancy", 1)[0]
        if occ.ndim != 3:  # pragma: no cover - check_occupancy saw 4 dims
            raise ValueError(f"occupancy: expected shape [X, Y, Z], got {occ.shape}")
        if self._grid is not None and occ.shape != self._grid:
            raise ValueError(
                f"occupancy: expected grid {self._grid} like the earlier frames, got {occ.shape}"
            )
        p = self.planner
        with torch.inference_mode():
            t0 = p._sync()
            frame = torch.from_numpy(np.array(occ, copy=True)).to(p.device)[None]
            if p.kind == "pose_warp":  # raw frames: the plan aligns and encodes them
                if occ.shape != tuple(p.grid.shape):
                    raise ValueError(
                        f"occupancy: expected the planner's grid {tuple(p.grid.shape)}, "
                        f"got {occ.shape}"
                    )
                self._tokens.append(frame[0])
            else:
                self._tokens.append(p.encode(frame).indices[0])
            ms = 1e3 * (p._sync() - t0)
        self._last_encode_ms += ms
        self._grid = tuple(occ.shape)
        self.frames_seen += 1
        return ms

    def plan(
        self,
        ego_displacements,
        command: str,
        forecast: bool = True,
        ego_yaws=None,
        check: bool = False,
        movers=None,
    ) -> PlanResult:
        """Plan from the last ``history_frames`` pushed frames.

        Args:
            ego_displacements: [T-1, 2] float metres, T-1 >= ``history_frames - 1`` (the last
                rows are used): ``d[i]`` between consecutive history frames, in the **current**
                ego frame; each step at most 50 m (see :class:`PlanRequest`).
            command: ``"left"``, ``"right"`` or ``"straight"``.
            forecast: also decode the occupancy forecast (False: trajectory only).
            ego_yaws: [T] float radians (T >= ``history_frames``, the last rows are used), the
                yaw of each history frame in the current ego frame (last 0); required by a
                pose-warp world model, ignored by a token world model.
            check: check the plan against the forecast (:meth:`Planner.plan_batch`; pose-warp
                world models only). The session remembers the fastest the ego drove since its
                last reset (its cruise speed): a plan stalled far below it while the ego stands
                gets candidates that go on at it (:class:`renderworld.planning.CheckConfig`);
                when the previous checked plan was made one frame before, its path is carried
                on to now and the new candidates start on it
                (:func:`renderworld.planning.checked.blend_with_previous`).
            movers: the mover forecast the check reads instead of the model's (a
                :data:`~renderworld.planning.scene.MoverForecaster`; None: the model's). A
                privileged one measures how much of the checked plan's score the forecast costs.

        Returns:
            :class:`PlanResult`; ``timings["encode"]`` is the encode time of the pushes since
            the previous plan (0 when none).

        Raises:
            ValueError: fewer than ``history_frames`` frames pushed, or a bad argument.
        """
        h = self.history_frames
        if not self.ready:
            raise ValueError(
                f"session: expected {h} pushed frames before planning, got {len(self._tokens)}"
            )
        disp = as_numpy(ego_displacements, "ego_displacements")
        rows = disp.shape[0] if disp.ndim == 2 and disp.shape[0] >= h - 1 else h - 1
        disp = check_displacements(disp, rows)[-(h - 1) :]
        check_command(command)
        if not isinstance(forecast, bool):
            raise TypeError(f"forecast: expected a bool, got {forecast!r}")
        if not isinstance(check, bool):
            raise TypeError(f"check: expected a bool, got {check!r}")
        if movers is not None and not check:
            raise ValueError("movers: only the check reads a mover forecast; pass check=True")
        if self.planner.kind == "pose_warp":
            if ego_yaws is None:
                raise ValueError(
                    "ego_yaws: the pose-warp world model needs the yaw of each history frame "
                    "([T] radians, current ego frame), got None"
                )
            yaws = as_numpy(ego_yaws, "ego_yaws")
            n = yaws.shape[0] if yaws.ndim == 1 and yaws.shape[0] >= h else h
            yaws = check_yaws(yaws, n)[-h:]
            frames = torch.stack(list(self._tokens))[None]  # [1, H, X, Y, Z]
            self._last_encode_ms = 0.0
            step = float(np.hypot(disp[:, 0], disp[:, 1]).max()) / KEYFRAME_DT
            self._cruise = max(self._cruise, step)
            previous = self._carried_previous(disp, yaws) if check else None
            plan = self.planner._plan_frames
            result = plan(frames, disp[None], yaws[None], [command], forecast, check,
                          [self._cruise], [previous], movers)[0]  # fmt: skip
            if check:
                self._previous = (self.frames_seen, np.asarray(result.trajectory, np.float64))
            return result
        self.planner._refuse_check(check)
        history = torch.stack(list(self._tokens))[None]  # [1, H, G, h, w]
        encode_ms, self._last_encode_ms = self._last_encode_ms, 0.0
        return self.planner._plan_tokens(
            history, disp.astype(np.float32)[None], [command], forecast, encode_ms
        )[0]

    def _carried_previous(self, disp: np.ndarray, yaws: np.ndarray) -> np.ndarray | None:
        """The previous checked trajectory in the current ego frame, one step on ([S, 2]: its
        positions at +0.5 ... +2.5 s from its frame are this frame's first S - 1, the last one
        continued), or None when it was not made exactly one frame before."""
        if self._previous is None or self._previous[0] != self.frames_seen - 1:
            return None
        prev = self._previous[1]
        c, s = np.cos(yaws[-2]), np.sin(yaws[-2])  # the previous frame in the current one
        xy = prev @ np.array([[c, s], [-s, c]]) - disp[-1].astype(np.float64)
        return np.concatenate([xy[1:], xy[-1:] + (xy[-1:] - xy[-2:-1])])

    def step(
        self, occupancy, ego_displacements, command: str, forecast: bool = True, ego_yaws=None
    ):
        """:meth:`push` the new frame, then :meth:`plan` if the history is full (else None)."""
        self.push(occupancy)
        if not self.ready:
            return None
        return self.plan(ego_displacements, command, forecast, ego_yaws)
