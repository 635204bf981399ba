"""Planner latency through the public planner path (:mod:`renderworld.planning`).

One home for what ``benchmarks/bench_planner.py`` and the sweep's ``planner`` and
``world_model`` points share: the models of the two grids (the main job's mini 50x50x4, and
paper-sized untrained models at the Occ3D 200x200x16 grid), a street-like request, the streaming
call that is timed (``PlannerSession.push`` of the new frame + ``plan``), requests built from
world-model validation windows, :func:`time_plans` (batch 1, warm-up, best of ``repeats`` per
request, median over requests) and a point's CPU seconds (:func:`cpu_seconds`).

Torch and numpy only (no Hydra): the sweep's points and the benchmark scripts import it.
"""

from __future__ import annotations

import resource
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from renderworld.constants import COMMANDS, FREE_ID, HISTORY_FRAMES
from renderworld.planning import Planner, PlannerSession, PlanRequest, PlanResult, load_planner
from renderworld.tokenizer import TokenizerConfig, build_tokenizer
from renderworld.world import WorldModel, WorldModelConfig
from renderworld.world.tracks import clear_track_cache

__all__ = [
    "cpu_seconds",
    "make_request",
    "mini_models",
    "occ3d_models",
    "pose_warp_model",
    "requests_from_windows",
    "session_runner",
    "time_plans",
    "bundle_planner",
]


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (a 1-thread point's cost, which other
    processes' load does not inflate the way it inflates wall time)."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def make_request(grid, history: int, rng: np.random.Generator) -> PlanRequest:
    """A street-like history: road at z=0, scattered objects at z=1, 4 m per 0.5 s forward.

    Args:
        grid: (X, Y, Z) voxels. history: frames. rng: numpy generator (object positions).
    """
    occ = np.full((history, *grid), FREE_ID, dtype=np.uint8)
    occ[..., 0] = 11
    n = grid[0] * grid[1] // 50
    xs, ys = rng.integers(0, grid[0], n), rng.integers(0, grid[1], n)
    occ[:, xs, ys, 1] = rng.integers(1, 17, n)
    disp = np.tile([[4.0, 0.1]], (history - 1, 1))
    yaws = np.linspace(-0.05 * (history - 1), 0.0, history)  # read by pose-warp models only
    return PlanRequest(occ, disp, "straight", ego_yaws=yaws)


def _models(tok_cfg: TokenizerConfig, **wm) -> tuple:
    torch.manual_seed(0)
    tok = build_tokenizer(tok_cfg)
    cfg = WorldModelConfig(
        codebook_sizes=tuple(tok.cfg.codebook_sizes), token_grid=tuple(tok.cfg.latent_shape), **wm
    )
    return tok, WorldModel(cfg)


def bundle_planner(world_model_ckpt: Path, tokenizer_ckpt: Path, **options) -> Planner:
    """``load_planner`` of a bundle exported from a world-model and its tokenizer checkpoint.

    Either forecaster (``tokens`` or ``pose_warp``); ``options`` go to :class:`Planner`.
    """
    from renderworld.training.stages.world_model import export_planner_bundle

    with tempfile.TemporaryDirectory() as tmp:
        bundle = export_planner_bundle(world_model_ckpt, tokenizer_ckpt, Path(tmp) / "p.pt")
        return load_planner(bundle, **options)


def mini_models(tokenizer_ckpt: Path, world_model_ckpt: Path) -> tuple[tuple, str]:
    """(tokenizer, world model) of the given checkpoints when both exist, else untrained models
    of the mini sizes (tokenizer_mini / world_model_mini); and which it is."""
    if tokenizer_ckpt.is_file() and world_model_ckpt.is_file():
        p = bundle_planner(world_model_ckpt, tokenizer_ckpt)
        return (p.tokenizer, p.world_model), "demo checkpoints"
    tok = TokenizerConfig(
        grid_shape=(50, 50, 4), latent_shape=(25, 25), latent_channels=64, codebook_size=1024,
        base_channels=32, num_res_blocks=1, attention=False,
    )  # fmt: skip
    models = _models(tok, embed_dim=64, num_heads=4, num_scales=2, layers_per_scale=(1, 1))
    return models, "untrained, mini sizes (no demo checkpoints)"


def occ3d_models() -> tuple:
    """Paper-sized AM-VAE + default-width world model at 200x200x16, untrained weights."""
    return _models(
        TokenizerConfig(), embed_dim=128, num_heads=4, num_scales=3, layers_per_scale=(2, 2, 2)
    )


def pose_warp_model(wm, movers: str = "static"):
    """The pose-warp world model (the main job's kind) of ``wm``'s config, untrained, seed 0,
    with ``movers`` (``learned``: with a mover head); ``wm`` itself when it is one (the demo's
    checkpoints)."""
    from renderworld.world.pose import PoseWarpWorldModel

    if isinstance(wm, PoseWarpWorldModel):
        return wm
    torch.manual_seed(0)
    return PoseWarpWorldModel(wm.config, anchors="ctr_cv", movers=movers)  # world_model_mini's


def session_runner(
    forecast: bool, check: bool = False
) -> Callable[[Planner, PlanRequest, PlannerSession], dict]:
    """The streaming call of a car's loop: push the request's newest frame (one encode), plan
    from the session's history (``check``: checked against the forecast); returns
    ``PlanResult.timings`` + ``wall`` (ms) + ``result``."""

    def run(planner: Planner, req: PlanRequest, session: PlannerSession) -> dict:
        clear_track_cache()  # each plan tracks its history once, as a new history would
        t0 = time.perf_counter()
        session.push(req.occupancy[-1])
        res = session.plan(req.ego_displacements, req.command, forecast, req.ego_yaws, check)
        return {**res.timings, "wall": 1e3 * (time.perf_counter() - t0), "result": res}

    return run


def requests_from_windows(batch: dict, history: int) -> list[PlanRequest]:
    """One request per window of a collated world-model batch: its history only.

    A request holds at least ``HISTORY_FRAMES`` (5) frames; a shorter history is padded in
    front with its oldest frame standing still (the planner reads the last ``history_frames``).

    Args:
        batch: ``occ`` [B, T, X, Y, Z] uint8, ``history_poses`` [B, history, 3] (x, y metres,
            yaw radians, in the current ego frame), ``command`` [B].
        history: the windows' history frames (the planner's ``history_frames``).
    """
    poses = batch["history_poses"].double().cpu().numpy()[:, -history:]
    occ = batch["occ"][:, :history].cpu().numpy()
    pad = max(0, HISTORY_FRAMES - history)
    out = []
    for i in range(occ.shape[0]):
        p = np.concatenate([np.repeat(poses[i, :1], pad, axis=0), poses[i]])
        o = np.concatenate([np.repeat(occ[i, :1], pad, axis=0), occ[i]])
        command = COMMANDS[int(batch["command"][i])]
        out.append(PlanRequest(o, np.diff(p[:, :2], axis=0), command, ego_yaws=p[:, 2]))
    return out


def time_plans(
    planner: Planner,
    requests: Sequence[PlanRequest],
    forecast: bool,
    repeats: int,
    warmup: int,
    check: bool = False,
) -> tuple[float, list[PlanResult]]:
    """Median over requests of the best-of-``repeats`` ms of one streaming plan, batch 1.

    Each call starts a fresh history: the session is reset and given the request's older frames
    (not timed); the timed call pushes the newest frame and plans (:func:`session_runner`).
    ``warmup`` untimed calls on the first request come first.

    Returns:
        (median ms, the first call's :class:`PlanResult` per request).

    Raises:
        ValueError: no requests, or ``repeats`` < 1.
    """
    if not requests:
        raise ValueError("requests: expected at least one request")
    if not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"repeats: expected an int >= 1, got {repeats!r}")
    run = session_runner(forecast, check)
    session = PlannerSession(planner)
    h = session.history_frames

    def once(req: PlanRequest) -> dict:
        session.reset()
        for frame in req.occupancy[-h:-1]:
            session.push(frame)
        return run(planner, req, session)

    for _ in range(warmup):
        once(requests[0])
    times, results = [], []
    for req in requests:
        outs = [once(req) for _ in range(repeats)]
        times.append(min(o["wall"] for o in outs))
        results.append(outs[0]["result"])
    return float(statistics.median(times)), results
