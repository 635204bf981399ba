"""Planner latency: ``Planner.plan`` median wall time at the mini grid and at the Occ3D grid.

Usage::

    PYTHONPATH=. python benchmarks/bench_planner.py [--device cpu] [--reps 10] [--threads 1 2]
        [--mini-tokenizer outputs/demo/tokenizer/checkpoints/best.pt]
        [--mini-world-model outputs/demo/world_model/checkpoints/best.pt]

Cases (both use the real AM-VAE tokenizer and the real world model, no stand-in):

* ``mini 50x50x4``: the main job's trained checkpoints (``make demo``: tokenizer_mini and
  world_model_mini), bundled with ``export_planner_bundle`` and loaded with ``load_planner``,
  exactly what a user of the planner API runs. Skipped (with a line saying so) when the
  checkpoints are missing.
* ``Occ3D 200x200x16``: a tokenizer built at the paper's sizes (``TokenizerConfig()`` defaults:
  AM-VAE, latent 50x50, 128 channels, 512 codes) and the world model at the stage's default
  width (D=128, 4 heads, 3 scales x 2 blocks), **untrained weights**: latency depends on the
  shapes, not on the weights (the rollout's argmax codes change, not the work done).

Rollout: 5 history frames, 6 steps (KV-cached, as ``Planner.plan`` runs it). Timings are medians
over ``--reps`` calls after 2 warm-up calls, per torch intra-op thread count; ``encode`` /
``world`` / ``decode`` are the planner's own stage timings (``PlanResult.timings``).
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.constants import FREE_ID  # noqa: E402
from renderworld.planning import Planner, PlanRequest, load_planner  # noqa: E402
from renderworld.tokenizer import TokenizerConfig, build_tokenizer  # noqa: E402
from renderworld.world import WorldModel, WorldModelConfig  # noqa: E402

DEMO = Path("outputs/demo")


def make_request(grid, history, rng) -> PlanRequest:
    """A street-like history: road at z=0, scattered objects at z=1, 4 m per 0.5 s forward."""
    occ = np.full((history, *grid), FREE_ID, dtype=np.uint8)
    occ[..., 0] = 11
    n = grid[0] * grid[1] // 50
    xs, ys = rng.integers(0, grid[0], n), rng.integers(0, grid[1], n)
    occ[:, xs, ys, 1] = rng.integers(1, 17, n)
    disp = np.tile([[4.0, 0.1]], (history - 1, 1))
    return PlanRequest(occ, disp, "straight")


def mini_planner(tokenizer_ckpt: Path, world_model_ckpt: Path, device: str) -> Planner | None:
    """The demo's trained planner (bundle written to a temp folder), or None when missing."""
    if not (tokenizer_ckpt.is_file() and world_model_ckpt.is_file()):
        return None
    from renderworld.training.stages.world_model import export_planner_bundle

    with tempfile.TemporaryDirectory() as tmp:
        bundle = export_planner_bundle(world_model_ckpt, tokenizer_ckpt, Path(tmp) / "p.pt")
        return load_planner(bundle, device=device)


def occ3d_planner(device: str) -> Planner:
    """Paper-sized AM-VAE + default-width world model at 200x200x16, untrained weights."""
    torch.manual_seed(0)
    tok = build_tokenizer(TokenizerConfig())  # defaults = the paper's Occ3D setting
    cfg = WorldModelConfig(
        codebook_sizes=tuple(tok.cfg.codebook_sizes), token_grid=tuple(tok.cfg.latent_shape),
        embed_dim=128, num_heads=4, num_scales=3, layers_per_scale=(2, 2, 2),
    )  # fmt: skip
    return Planner(tok, WorldModel(cfg), device=device)


def bench(planner: Planner, grid, reps: int) -> dict[str, float]:
    """Median stage timings (ms) of ``planner.plan`` on one request."""
    req = make_request(grid, planner.config.history_frames, np.random.default_rng(0))
    for _ in range(2):
        planner.plan(req)
    runs = []
    for _ in range(reps):
        t0 = time.perf_counter()
        res = planner.plan(req)
        runs.append({**res.timings, "wall": 1e3 * (time.perf_counter() - t0)})
    med = {k: statistics.median(r[k] for r in runs) for k in ("encode", "world_model", "decode")}
    med["wall"] = statistics.median(r["wall"] for r in runs)
    med["min"] = min(r["wall"] for r in runs)
    med["params_M"] = (
        sum(p.numel() for p in planner.world_model.parameters())
        + sum(p.numel() for p in planner.tokenizer.parameters())
    ) / 1e6
    return med


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch threads")
    ap.add_argument("--mini-tokenizer", type=Path, default=DEMO / "tokenizer/checkpoints/best.pt")
    ap.add_argument(
        "--mini-world-model", type=Path, default=DEMO / "world_model/checkpoints/best.pt"
    )
    ap.add_argument("--skip-occ3d", action="store_true")
    args = ap.parse_args()
    print(
        f"# Planner.plan latency (ms), device={args.device}, median of {args.reps} calls after "
        "2 warm-up calls; 5 history frames, 6-step KV-cached rollout, batch 1.\n"
        "# mini: the demo's trained tokenizer + world model; Occ3D: AM-VAE at the paper's sizes "
        "(latent 50x50, 128 ch, 512 codes) + world model D=128 3x2 blocks, untrained weights."
    )
    header = (
        f"{'grid':<18}{'threads':>8}{'tokens':>8}{'params M':>10}{'encode':>9}{'world':>9}"
        f"{'decode':>9}{'median':>10}{'min':>9}{'plans/s':>9}"
    )
    print(header)
    for threads in args.threads:
        torch.set_num_threads(threads)
        cases = [("mini 50x50x4", mini_planner(args.mini_tokenizer, args.mini_world_model,
                                               args.device))]  # fmt: skip
        if not args.skip_occ3d:
            cases.append(("Occ3D 200x200x16", occ3d_planner(args.device)))
        for name, planner in cases:
            if planner is None:
                print(f"{name:<18}{threads:>8}  skipped: no checkpoints at {args.mini_tokenizer} "
                      f"/ {args.mini_world_model} (run make demo or pass --mini-*)")  # fmt: skip
                continue
            grid = tuple(int(v) for v in name.split()[1].split("x"))
            m = bench(planner, grid, args.reps)
            toks = "x".join(map(str, planner.config.token_grid))
            print(
                f"{name:<18}{threads:>8}{toks:>8}{m['params_M']:>10.2f}{m['encode']:>9.1f}"
                f"{m['world_model']:>9.1f}{m['decode']:>9.1f}{m['wall']:>10.1f}{m['min']:>9.1f}"
                f"{1e3 / m['wall']:>9.2f}",
                flush=True,
            )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"# peak process RSS {rss:.0f} MB")


if __name__ == "__main__":
    main()
