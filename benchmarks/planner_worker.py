"""One side of ``bench_planner.py --baseline``: a planner from a given source tree, timed on demand.

    python benchmarks/planner_worker.py --tree DIR --case mini|occ3d --threads N --modes M ...

Imports ``renderworld`` from ``DIR`` (this checkout, or an older commit extracted by the driver),
builds untrained models with fixed seeds, prints ``ready``, then for every ``go`` line on stdin
runs each mode once and prints one JSON line ``{mode: {encode, world_model, decode, wall}}`` (ms).
Only API that every compared version has is used for the token modes (``Planner``,
``PlannerSession``, ``PlanRequest``); the pose-warp modes need this checkout's planner.

Modes (one new frame per plan, streaming session unless noted):

* ``today``: ``Planner(fast=False).plan(request)``: five encodes, reference codec (no session).
* ``full`` / ``traj``: token world model, session, forecast on / off.
* ``full bf16``: ``full`` with the bf16 decoder.
* ``pw full`` / ``pw traj``: pose-warp world model (``stage.forecaster=pose_warp``), session,
  forecast on / off.

``--retain-memory`` calls :func:`renderworld.planning.retain_freed_memory` first;
``--world-model-threads N`` passes ``Planner(world_model_threads=N)``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

MODES = ("today", "full", "traj", "full bf16", "pw full", "pw traj")
STAGES = ("encode", "world_model", "decode")


def _tokenizer_config(case: str):
    from renderworld.tokenizer import TokenizerConfig

    if case == "mini":  # experiment=tokenizer_mini
        return TokenizerConfig(
            grid_shape=(50, 50, 4), latent_shape=(25, 25), latent_channels=64, codebook_size=256,
            base_channels=32, num_res_blocks=1, attention=False,
        )  # fmt: skip
    return TokenizerConfig()  # the paper's AM-VAE at the Occ3D grid


def _world_model_kwargs(case: str) -> dict:
    if case == "mini":  # experiment=world_model_mini
        return {"embed_dim": 64, "num_heads": 4, "num_scales": 2, "layers_per_scale": (1, 1)}
    return {"embed_dim": 128, "num_heads": 4, "num_scales": 3, "layers_per_scale": (2, 2, 2)}


def build(case: str, pose_warp: bool):
    """(tokenizer, world model), untrained, seed 0 (latency depends on shapes, not weights)."""
    import torch

    from renderworld.tokenizer import build_tokenizer
    from renderworld.world import WorldModel, WorldModelConfig

    torch.manual_seed(0)
    tok = build_tokenizer(_tokenizer_config(case))
    cfg = WorldModelConfig(
        codebook_sizes=tuple(tok.cfg.codebook_sizes), token_grid=tuple(tok.cfg.latent_shape),
        **_world_model_kwargs(case),
    )  # fmt: skip
    if not pose_warp:
        return tok, WorldModel(cfg)
    from renderworld.world.pose import PoseWarpWorldModel

    return tok, PoseWarpWorldModel(cfg, anchors="ctr_cv")  # world_model_mini's anchors


def make_request(grid, history: int, seed: int = 0, yaws: bool = False):
    """A street: road at z=0, scattered objects at z=1, 4 m per 0.5 s forward, a gentle left."""
    import numpy as np

    from renderworld.constants import FREE_ID
    from renderworld.planning import PlanRequest

    rng = np.random.default_rng(seed)
    occ = np.full((history, *grid), FREE_ID, dtype=np.uint8)
    occ[..., 0] = 11
    n = grid[0] * grid[1] // 50
    xs, ys = rng.integers(0, grid[0], n), rng.integers(0, grid[1], n)
    occ[:, xs, ys, 1] = rng.integers(1, 17, n)
    disp = np.tile([[4.0, 0.1]], (history - 1, 1))
    if not yaws:
        return PlanRequest(occ, disp, "straight")
    return PlanRequest(
        occ, disp, "straight", ego_yaws=np.linspace(-0.05 * (history - 1), 0, history)
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", required=True)
    ap.add_argument("--case", choices=("mini", "occ3d"), required=True)
    ap.add_argument("--threads", type=int, required=True)
    ap.add_argument("--modes", nargs="+", choices=MODES, required=True)
    ap.add_argument("--retain-memory", action="store_true", help="retain_freed_memory() first")
    ap.add_argument("--world-model-threads", type=int, default=None)
    args = ap.parse_args()
    sys.path.insert(0, os.path.abspath(args.tree))
    import torch

    if args.retain_memory:
        from renderworld.planning import retain_freed_memory

        if not retain_freed_memory():
            raise SystemExit("retain_freed_memory: not available on this C library")

    from renderworld.planning import Planner, PlannerSession

    torch.set_num_threads(args.threads)
    grid = tuple(_tokenizer_config(args.case).grid_shape)
    planners, sessions, runs = {}, {}, {}
    req_tok = make_request(grid, 5)
    req_pw = (
        make_request(grid, 5, yaws=True) if any(m.startswith("pw") for m in args.modes) else None
    )

    def planner(key):
        if key not in planners:
            tok, wm = build(args.case, key.startswith("pw"))
            opts = {"fast": key != "today"}
            if args.world_model_threads:
                opts["world_model_threads"] = args.world_model_threads
            if key == "bf16":
                opts["precision"] = "bfloat16"
            planners[key] = Planner(tok, wm, **opts)
        return planners[key]

    def session(key, req):
        if key not in sessions:
            s = PlannerSession(planner(key))
            for frame in req.occupancy[:-1]:
                s.push(frame)
            sessions[key] = s
        return sessions[key]

    for mode in args.modes:
        if mode == "today":
            p = planner("today")
            runs[mode] = lambda p=p: p.plan(req_tok)
            continue
        key = {"full": "fast", "traj": "fast", "full bf16": "bf16"}.get(mode, "pw")
        req = req_pw if key == "pw" else req_tok
        s, forecast = session(key, req), not mode.endswith("traj")
        extra = {"ego_yaws": req.ego_yaws} if key == "pw" else {}

        def run(s=s, req=req, forecast=forecast, extra=extra):
            s.push(req.occupancy[-1])  # the new frame
            return s.plan(req.ego_displacements, req.command, forecast=forecast, **extra)

        runs[mode] = run
    try:  # each plan tracks its history once, as a new history would (no cache before it)
        from renderworld.world.tracks import clear_track_cache
    except ImportError:
        clear_track_cache = lambda: None  # noqa: E731
    print("ready", flush=True)
    for line in sys.stdin:
        if line.strip() != "go":
            break
        out = {}
        for mode, run in runs.items():
            clear_track_cache()
            t0 = time.perf_counter()
            res = run()
            wall = 1e3 * (time.perf_counter() - t0)
            out[mode] = {**{k: float(res.timings.get(k, 0.0)) for k in STAGES}, "wall": wall}
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
