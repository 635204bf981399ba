"""The planner API: occupancy history + current command -> 3 s trajectory and forecast.

Two kinds of world model plan behind the same API: the token world model
(:class:`renderworld.world.WorldModel`, ``stage.forecaster=tokens``: an autoregressive rollout
of scene tokens and ego displacements) and the pose-warp world model
(:class:`renderworld.world.pose.PoseWarpWorldModel`, ``stage.forecaster=pose_warp``, the main
job's: predicted future poses, the current frame warped along them, the token network's fill;
see :mod:`renderworld.planning.pose_warp`). The pose-warp model also reads the history frames'
yaws (``PlanRequest.ego_yaws``).

Frames and units: :mod:`renderworld.planning.request`. The planner uses the last
``history_frames`` (5) frames when more are given, and holds the current command fixed through
the rollout. For a car's loop (one new frame at a time) use
:class:`renderworld.planning.PlannerSession`, which encodes each frame once.

Execution options (:class:`Planner`):

* ``fast`` (default True): the package's :class:`SceneTokenizer` runs through
  :class:`renderworld.tokenizer.inference.FastSceneCodec` (channels-last, no full-resolution
  log-probabilities; on a CPU as many frames per pass as the last-level cache holds: one at
  the Occ3D grid); ``fast=False`` runs ``tokenizer.encode`` / ``tokenizer.decode``, the
  reference path (and the only path for other tokenizers).
* ``precision``: ``"float32"`` (default) or ``"bfloat16"``: ``torch.autocast`` around the
  occupancy decoder only, the FLOP-heavy stage. The encoder and the world model stay float32,
  so history tokens and trajectories are exactly those of float32 (bf16 in the rollout moved
  waypoints by up to ~2 % of the path with untrained weights, and the rollout is launch-bound,
  not FLOP-bound, on a GPU). Only forecast voxels can change (tests bound the fraction).
* ``compile``: None (default) or a ``torch.compile`` mode for the decoder (``"default"``,
  ``"reduce-overhead"`` = CUDA graphs on a GPU, ``"max-autotune"``); if compiling fails the
  planner warns once and runs eagerly. Other errors of the compiled decoder (out of memory, a
  shape bug) are raised as they are and leave it compiled.
* ``pin_memory``: copy the forecast into pinned host memory (CUDA only; default on for CUDA).
* ``world_model_threads``: torch intra-op threads while the world model runs (None: the
  process's setting). The mini world model's ops are small (625 cells x 64 channels): on a CPU
  one thread runs its rollout faster than two, which wait on each other at every op, while the
  encoder and decoder convolutions still use every thread. The setting is restored after each
  call (it is process-wide: do not plan from several Python threads with it set).
"""

from __future__ import annotations

import contextlib
import time
import warnings

import numpy as np
import torch

from renderworld.constants import COMMANDS, GridSpec
from renderworld.planning.candidates import CheckConfig
from renderworld.planning.checked import check_plan
from renderworld.planning.compiled import is_compile_failure
from renderworld.planning.pose_warp import (
    check_tokens,
    default_grid,
    forecast_from_poses,
    history_poses,
    tokenizer_grid_shape,
)
from renderworld.planning.request import PlanRequest, PlanResult, as_numpy, stack_requests
from renderworld.planning.scene import model_forecaster
from renderworld.tokenizer import SceneTokenizer
from renderworld.tokenizer.inference import FastSceneCodec, cache_frames_per_pass
from renderworld.tokenizer.tokens import Tokens
from renderworld.world.model import WorldModel
from renderworld.world.pose import PoseWarpWorldModel

__all__ = ["PlanRequest", "PlanResult", "Planner"]

PRECISIONS = {"float32": None, "bfloat16": torch.bfloat16}
COMPILE_MODES = (None, "default", "reduce-overhead", "max-autotune")


class Planner:
    """Tokenizer + world model behind a small, validated API.

    Args:
        tokenizer: object with ``encode(occ [B, X, Y, Z] uint8) -> Tokens`` and
            ``decode(Tokens) -> [B, X, Y, Z] uint8`` (an ``nn.Module`` is moved to ``device``
            and set to eval mode).
        world_model: :class:`renderworld.world.WorldModel` or
            :class:`renderworld.world.pose.PoseWarpWorldModel` whose codebooks and token grid
            match the tokenizer's.
        device: where both run.
        grid: the occupancy grid (x/y range and voxel size), read by the pose-warp model's warps
            (None: the Occ3D range on the tokenizer's ``grid_shape``, as every named grid).
        fast: use the fast inference codec for a :class:`SceneTokenizer` (see module doc).
        precision: ``"float32"`` or ``"bfloat16"`` (the decoder's autocast dtype).
        compile: None or a ``torch.compile`` mode for the decoder.
        pin_memory: pinned host memory for the forecast copy (None: on for CUDA devices).
        world_model_threads: intra-op threads of the world model's part (None: unchanged).
        check_config: knobs of the forecast-checked plan (None: :class:`CheckConfig`'s).
    """

    def __init__(
        self,
        tokenizer,
        world_model: WorldModel | PoseWarpWorldModel,
        device: str | torch.device = "cpu",
        *,
        grid: GridSpec | None = None,
        fast: bool = True,
        precision: str = "float32",
        compile: str | None = None,
        pin_memory: bool | None = None,
        world_model_threads: int | None = None,
        check_config: CheckConfig | None = None,
    ):
        for name in ("encode", "decode"):
            if not callable(getattr(tokenizer, name, None)):
                raise TypeError(f"tokenizer: expected an object with a callable .{name}()")
        if not isinstance(world_model, (WorldModel, PoseWarpWorldModel)):
            raise TypeError(
                "world_model: expected WorldModel or PoseWarpWorldModel, got "
                f"{type(world_model).__name__}"
            )
        if grid is not None and not isinstance(grid, GridSpec):
            raise TypeError(f"grid: expected a GridSpec or None, got {type(grid).__name__}")
        if not isinstance(fast, bool):
            raise TypeError(f"fast: expected a bool, got {fast!r}")
        if precision not in PRECISIONS:
            raise ValueError(f"precision: expected one of {tuple(PRECISIONS)}, got {precision!r}")
        if compile not in COMPILE_MODES:
            raise ValueError(f"compile: expected one of {COMPILE_MODES}, got {compile!r}")
        if world_model_threads is not None and (
            type(world_model_threads) is not int or world_model_threads < 1
        ):
            raise ValueError(
                f"world_model_threads: expected None or an int >= 1, got {world_model_threads!r}"
            )
        if check_config is not None and not isinstance(check_config, CheckConfig):
            raise TypeError(
                f"check_config: expected a CheckConfig or None, got {type(check_config).__name__}"
            )
        #: Knobs of the forecast-checked plan (``check=True``).
        self.check_config = check_config or CheckConfig()
        self.world_model_threads = world_model_threads
        self.device = torch.device(device)
        if pin_memory is None:
            pin_memory = self.device.type == "cuda"
        if pin_memory and self.device.type != "cuda":
            raise ValueError(f"pin_memory: only applies to CUDA devices, got {self.device}")
        self.tokenizer = tokenizer
        self.world_model = world_model.to(self.device).eval()
        if isinstance(tokenizer, torch.nn.Module):
            self.tokenizer = tokenizer.to(self.device).eval()
        self.config = world_model.config
        self.kind = "pose_warp" if isinstance(world_model, PoseWarpWorldModel) else "tokens"
        shape = tokenizer_grid_shape(tokenizer)
        if grid is None and shape is not None:
            grid = default_grid(shape)
        if grid is None and self.kind == "pose_warp":
            raise ValueError(
                "grid: a pose-warp world model needs the occupancy grid; the tokenizer names no "
                "grid_shape, pass grid="
            )
        if grid is not None and shape is not None and tuple(grid.shape) != shape:
            raise ValueError(
                f"grid: expected the tokenizer's grid_shape {shape}, got {tuple(grid.shape)}"
            )
        self.grid = grid
        self.fast, self.precision, self.compile = fast, precision, compile
        self.pin_memory = bool(pin_memory)
        codec = None
        if fast and isinstance(tokenizer, SceneTokenizer):  # a GPU codes all frames in one pass
            per_pass = cache_frames_per_pass(tokenizer) if self.device.type == "cpu" else None
            codec = FastSceneCodec(self.tokenizer, max_batch=per_pass)
        self._encode_fn = codec.encode if codec else self.tokenizer.encode
        self._decode_fn = codec.decode if codec else self.tokenizer.decode
        self._names: tuple[str, ...] = ()  # codebook names, from the tokenizer's first encode
        self._compiled = None
        if compile is not None:
            self._compiled = torch.compile(self._decode_fn, mode=compile, dynamic=False)

    # ------------------------------------------------------------------ stages
    def _sync(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def _autocast(self):
        dtype = PRECISIONS[self.precision]
        if dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=dtype)

    @contextlib.contextmanager
    def _world_model_threads(self):
        """``world_model_threads`` intra-op threads inside, the previous count restored after."""
        before = torch.get_num_threads()
        n = self.world_model_threads
        if n is None or n == before:
            yield
            return
        torch.set_num_threads(n)
        try:
            yield
        finally:
            torch.set_num_threads(before)

    def encode(self, occ: torch.Tensor) -> Tokens:
        """Occupancy [N, X, Y, Z] uint8 (on ``device``) -> checked :class:`Tokens` [N, G, h, w]."""
        tokens = self._encode_fn(occ)
        check_tokens(tokens, self.config, occ.shape[0])
        self._names = tuple(tokens.codebook_names)
        return tokens

    def _decode(self, tokens: Tokens) -> torch.Tensor:
        if self._compiled is not None:
            try:
                return self._compiled(tokens)
            except Exception as err:
                if not is_compile_failure(err):  # out of memory, a shape bug: the caller's
                    raise
                warnings.warn(  # not compiled (no compiler, an op it cannot lower): run eagerly
                    f"compile={self.compile!r}: torch.compile failed ({type(err).__name__}: "
                    f"{str(err)[:200]}); running the decoder eagerly",
                    RuntimeWarning,
                    stacklevel=3,
                )
                self._compiled = None
        return self._decode_fn(tokens)

    def _decode_codes(self, indices: torch.Tensor) -> torch.Tensor:
        """Codes [N, G, h, w] -> occupancy [N, X, Y, Z] (decoder autocast and compile)."""
        tokens = Tokens(indices, tuple(self.config.codebook_sizes), self._names)
        with self._autocast():
            return self._decode(tokens)

    def _plan_frames(
        self,
        occ: torch.Tensor,
        displacements: np.ndarray,
        yaws: np.ndarray,
        commands: list[str],
        forecast: bool = True,
        check: bool = False,
        cruise: list[float] | None = None,
        previous: list | None = None,
        movers=None,
    ) -> list[PlanResult]:
        """Plan with the pose-warp model from raw history frames (shared by :meth:`plan_batch`
        and :class:`renderworld.planning.PlannerSession`; inputs are assumed validated).

        Args:
            occ: [B, H, X, Y, Z] uint8 on ``device``, H = ``history_frames``.
            displacements: [B, H-1, 2] float metres, current ego frame.
            yaws: [B, H] radians, current ego frame.
            commands: B commands.
            forecast: also forecast the occupancy (False: the pose head only).
            check: check the plan against the forecast (:mod:`renderworld.planning.checked`).
            cruise: B speeds (m/s) the ego drove at recently, for the check (None: each
                history's fastest step).
            previous: B previous trajectories carried on to now ([S, 2] or None), for the
                check (:func:`renderworld.planning.checked.check_plan`).
            movers: the check's mover forecast (None: the model's own, ``model_forecaster``).
        """
        b = occ.shape[0]
        s = self.config.future_frames
        cmd = torch.tensor([COMMANDS.index(c) for c in commands], device=self.device)
        ms = {"encode": 0.0, "world_model": 0.0, "decode": 0.0}
        with torch.inference_mode():
            t0 = self._sync()
            hist = history_poses(displacements, yaws).to(self.device)
            with self._world_model_threads():
                poses, _ = self.world_model.predict_poses(hist, cmd, occ[:, -1], occ, self.grid)
            traj = poses[..., :2].float().cpu().numpy()
            yaw = poses[..., 2].float().cpu().numpy()
            ms["world_model"] = 1e3 * (self._sync() - t0)
            fc = None
            if forecast:
                dec, more = forecast_from_poses(self, occ, hist, poses, cmd)
                fc = self._to_host(dec.flatten(0, 1), b * s).reshape(b, s, *dec.shape[2:])
                ms = {k: ms[k] + more[k] for k in ms}
            checks = [None] * b
            if check:
                h_np, p_np, o_np = (t.cpu().numpy() for t in (hist.double(), poses.double(), occ))
                movers = model_forecaster(self.world_model) if movers is None else movers
                cruise, previous = cruise or [None] * b, previous or [None] * b
                checks = [check_plan(o_np[i], h_np[i], p_np[i], self.grid, self.check_config,
                                     movers=movers, cruise_speed=cruise[i],
                                     previous=previous[i]) for i in range(b)]  # fmt: skip
                ms["check"] = sum(c.timings["check"] for c in checks)
        timings = {**ms, "total": 1e3 * (self._sync() - t0), "batch_size": b}
        out = []
        for i, c in enumerate(checks):
            fc_i = None if fc is None else fc[i]
            if c is None:
                out.append(PlanResult(traj[i], fc_i, dict(timings), yaw[i]))
            else:
                t = {**timings, **{f"check_{k}": v for k, v in c.timings.items() if k != "check"}}
                out.append(PlanResult(c.trajectory, fc_i, t, yaw[i], traj[i], c.candidates))
        return out

    def _plan_tokens(
        self,
        history_tokens: torch.Tensor,
        displacements: np.ndarray,
        commands: list[str],
        forecast: bool = True,
        encode_ms: float = 0.0,
    ) -> list[PlanResult]:
        """Roll out from already encoded history tokens (shared by :meth:`plan_batch` and
        :class:`renderworld.planning.PlannerSession`; inputs are assumed validated).

        Args:
            history_tokens: [B, H, G, h, w] int64 on ``device``, H = ``history_frames``,
                from :meth:`encode`.
            displacements: [B, H-1, 2] float metres, current ego frame.
            commands: B commands.
            forecast: also decode the forecast occupancy (False: trajectory only, no decode).
            encode_ms: time already spent encoding, reported in the timings.
        """
        b = history_tokens.shape[0]
        s = self.config.future_frames
        cmd = torch.tensor([COMMANDS.index(c) for c in commands], device=self.device)
        disp = torch.from_numpy(np.asarray(displacements, dtype=np.float32)).to(self.device)
        with torch.inference_mode():
            t1 = self._sync()
            with self._world_model_threads():
                out = self.world_model.rollout(
                    history_tokens, disp, cmd, steps=s, trajectory_only=not forecast
                )
            traj = out.trajectory.float().cpu().numpy()
            t2 = self._sync()
            occ = None
            if forecast:
                dec = self._decode_codes(out.tokens.reshape(b * s, *out.tokens.shape[2:]))
                occ = self._to_host(dec, b * s)
            t3 = self._sync()
        timings = {
            "encode": encode_ms,
            "world_model": 1e3 * (t2 - t1),
            "decode": 1e3 * (t3 - t2),
            "total": encode_ms + 1e3 * (t3 - t1),
            "batch_size": b,
        }
        grid = None if occ is None else occ.shape[1:]
        return [
            PlanResult(traj[i], None if occ is None else occ.reshape(b, s, *grid)[i], dict(timings))
            for i in range(b)
        ]

    def _to_host(self, dec, n: int) -> np.ndarray:
        if not isinstance(dec, torch.Tensor) or dec.dim() != 4 or dec.shape[0] != n:
            raise ValueError(
                f"tokenizer: decode returned {getattr(dec, 'shape', type(dec))}, "
                f"expected [{n}, X, Y, Z]"
            )
        dec = dec.to(torch.uint8)
        if self.pin_memory and dec.device.type == "cuda":
            host = torch.empty(dec.shape, dtype=torch.uint8, pin_memory=True)
            host.copy_(dec, non_blocking=True)
            torch.cuda.current_stream(dec.device).synchronize()
            return host.numpy()
        return dec.cpu().numpy()

    # ------------------------------------------------------------------ public
    def plan(self, request: PlanRequest, forecast: bool = True, check: bool = False) -> PlanResult:
        """Plan for one request (see :meth:`plan_batch`)."""
        return self.plan_batch([request], forecast=forecast, check=check)[0]

    def plan_batch(self, requests, forecast: bool = True, check: bool = False) -> list[PlanResult]:
        """Plan for several requests in one batch (their grids must match).

        Inputs are never modified: the history is copied before use.

        Args:
            requests: :class:`PlanRequest` objects.
            forecast: also decode the occupancy forecast; False gives a trajectory-only plan
                (no occupancy decode, ``occupancy_forecast`` None, the same trajectory; with a
                pose-warp model: the pose head only, no encode either).
            check: check the plan against the forecast and drive the best candidate around it
                (:mod:`renderworld.planning.checked`; pose-warp models): ``trajectory`` is the
                chosen candidate's, ``raw_trajectory`` the model's own, ``candidates`` every
                candidate's scores; the forecast and ``yaws`` stay along the model's own plan.

        Raises:
            TypeError: a request is not a :class:`PlanRequest`.
            ValueError: empty list, grids that differ, tokens that do not fit the model, or
                (pose-warp model) a request without ``ego_yaws`` or off the planner's grid.
        """
        if not isinstance(forecast, bool):
            raise TypeError(f"forecast: expected a bool, got {forecast!r}")
        occ, disp, reqs = stack_requests(requests, self.config.history_frames)
        h, grid = self.config.history_frames, occ.shape[2:]
        b = len(reqs)
        if self.kind == "pose_warp":
            if grid != tuple(self.grid.shape):
                raise ValueError(
                    f"requests[0].occupancy: expected the planner's grid {tuple(self.grid.shape)}, "
                    f"got {grid}"
                )
            for i, r in enumerate(reqs):
                if r.ego_yaws is None:
                    raise ValueError(
                        f"requests[{i}].ego_yaws: the pose-warp world model needs the yaw of each "
                        "history frame ([T] radians, current ego frame), got None"
                    )
            yaws = np.stack([as_numpy(r.ego_yaws, "ego_yaws")[-h:] for r in reqs])
            frames = torch.from_numpy(occ).to(self.device)
            cmds = [r.command for r in reqs]
            return self._plan_frames(frames, disp, yaws, cmds, forecast, check)
        self._refuse_check(check)
        disp = disp.astype(np.float32)
        with torch.inference_mode():
            t0 = self._sync()
            tokens = self.encode(torch.from_numpy(occ).to(self.device).reshape(b * h, *grid))
            encode_ms = 1e3 * (self._sync() - t0)
        idx = tokens.indices.reshape(b, h, *tokens.indices.shape[1:])
        return self._plan_tokens(idx, disp, [r.command for r in reqs], forecast, encode_ms)

    def _refuse_check(self, check) -> None:
        if not isinstance(check, bool):
            raise TypeError(f"check: expected a bool, got {check!r}")
        if check and self.kind != "pose_warp":
            raise ValueError(
                "check: checking a plan against the forecast needs a pose-warp world model "
                "(stage.forecaster=pose_warp), this planner's is a token world model"
            )
