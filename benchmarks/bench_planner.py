"""Planner latency: ``Planner.plan`` median wall time per stage at two grid sizes.

Usage::

    PYTHONPATH=. python benchmarks/bench_planner.py [--device cpu] [--reps 10] [--threads N]

Tokenizer: a **stand-in** (``tests/world/fake_tokenizer.PatchTokenizer``: majority class and
occupied-height per BEV patch, no network) relabelled with 512 + 512 codes so the world model
has AM-VAE-sized heads; its encode/decode times are NOT those of the AM-VAE. The world model is
the real one at OccWorld-like width (D=128, 3 scales, 2 blocks each, random weights: latency
does not depend on the weights). Rollout: 5 history frames, 6 steps, no KV cache.
Timings are medians over ``--reps`` runs after 2 warm-up runs; "ratio" is relative to the
small grid measured in the same run; "world no-cache" is the rollout recomputing the whole
window every step (the reference of the KV-cached rollout), "cache x" its ratio to "world".
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.constants import FREE_ID  # noqa: E402
from renderworld.planning import Planner, PlanRequest  # noqa: E402
from renderworld.tokenizer.tokens import Tokens  # noqa: E402
from renderworld.world import WorldModel, WorldModelConfig  # noqa: E402
from tests.world.fake_tokenizer import PatchTokenizer, PatchTokenizerConfig  # noqa: E402

CODEBOOK = 512


class StandInTokenizer(torch.nn.Module):
    """PatchTokenizer codes reported as two 512-entry codebooks (AM-VAE sized)."""

    def __init__(self, grid, patch):
        super().__init__()
        self.inner = PatchTokenizer(PatchTokenizerConfig(grid, patch, 2))
        self.token_grid = self.inner.token_grid
        self.limits = self.inner.codebook_sizes

    def encode(self, occ):
        t = self.inner.encode(occ)
        return Tokens(t.indices, (CODEBOOK, CODEBOOK), t.codebook_names)

    def decode(self, tokens):
        idx = tokens.indices.clone()
        for g, k in enumerate(self.limits):
            idx[:, g].clamp_(0, k - 1)
        return self.inner.decode(Tokens(idx, self.limits, tokens.codebook_names))


def make_request(grid, rng):
    occ = np.full((5, *grid), FREE_ID, dtype=np.uint8)
    occ[..., 0] = 11
    n = grid[0] * grid[1] // 50
    xs, ys = rng.integers(0, grid[0], n), rng.integers(0, grid[1], n)
    occ[:, xs, ys, 1] = rng.integers(1, 17, n)
    disp = np.tile([[4.0, 0.1]], (4, 1))
    return PlanRequest(occ, disp, "straight")


def bench(grid, patch, device, reps):
    torch.manual_seed(0)
    tok = StandInTokenizer(grid, patch)
    cfg = WorldModelConfig(
        codebook_sizes=(CODEBOOK, CODEBOOK), token_grid=tok.token_grid, embed_dim=128,
        num_heads=4, num_scales=3, layers_per_scale=(2, 2, 2),
    )  # fmt: skip
    planner = Planner(tok, WorldModel(cfg), device=device)
    req = make_request(grid, np.random.default_rng(0))
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    for _ in range(2):
        planner.plan(req)
    runs = []
    for _ in range(reps):
        t0 = time.perf_counter()
        res = planner.plan(req)
        wall = 1e3 * (time.perf_counter() - t0)
        runs.append({**res.timings, "wall": wall})
    keys = ("encode", "world_model", "decode", "wall")
    med = {k: statistics.median(r[k] for r in runs) for k in keys}
    # Reference in the same run: the rollout recomputing the whole window every step.
    occ = torch.from_numpy(req.occupancy).to(device)
    with torch.inference_mode():
        idx = tok.encode(occ).indices[None]
        disp = torch.from_numpy(req.ego_displacements).float()[None].to(device)
        cmd = torch.tensor([2], device=device)
        ref = []
        for _ in range(max(3, reps // 2)):
            t0 = time.perf_counter()
            planner.world_model.rollout(idx, disp, cmd, use_cache=False)
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            ref.append(1e3 * (time.perf_counter() - t0))
    med["world_nocache"] = statistics.median(ref)
    med["params_M"] = sum(p.numel() for p in planner.world_model.parameters()) / 1e6
    med["gpu_peak_MB"] = (
        torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda") else float("nan")
    )
    return med


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0 = default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    cases = [("small 50x50x4", (50, 50, 4), 2), ("Occ3D 200x200x16", (200, 200, 16), 4)]
    print(
        f"# Planner.plan latency, device={args.device}, torch threads={torch.get_num_threads()}, "
        f"median of {args.reps} (ms). Stand-in tokenizer (patch majority, not the AM-VAE); "
        "world model D=128, 3 scales x 2 blocks, codebooks 2x512, 5 history + 6 rollout steps."
    )
    header = (
        f"{'grid':<18}{'tokens':>8}{'params M':>10}{'encode':>9}{'world':>10}{'decode':>9}"
        f"{'total':>10}{'ratio':>7}{'world no-cache':>16}{'cache x':>9}{'GPU MB':>9}"
    )
    print(header)
    ref = None
    for name, grid, patch in cases:
        m = bench(grid, patch, args.device, args.reps)
        ref = ref or m["wall"]
        toks = f"{grid[0] // patch}x{grid[1] // patch}"
        print(
            f"{name:<18}{toks:>8}{m['params_M']:>10.2f}{m['encode']:>9.1f}{m['world_model']:>10.1f}"
            f"{m['decode']:>9.1f}{m['wall']:>10.1f}{m['wall'] / ref:>7.2f}"
            f"{m['world_nocache']:>16.1f}{m['world_nocache'] / m['world_model']:>9.2f}"
            f"{m['gpu_peak_MB']:>9.0f}"
        )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"# peak process RSS {rss:.0f} MB")


if __name__ == "__main__":
    main()
