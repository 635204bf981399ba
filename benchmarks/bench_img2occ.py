"""Img2Occ training-step benchmark: time and peak memory, coarse vs full Occ3D grid, pruning.

One training step = ``model(batch)`` (encoder on C images, lifting, BEV head, rendering of
``--views`` cameras) + ``model.loss`` + ``backward``, with depth-aware lifting of
``--depth-bins`` bins (default 40, as experiment=img2occ_mini; 0 = mean lifting).
Configurations: grid coarse (50x50x4, 10k anchors) and occ3d (200x200x16, 640k anchors); pruning
off (``prune_opacity=0``: every Gaussian is rendered) and on (``prune_opacity=1/255``, lossless)
with a trained-like opacity field: the head's opacity bias puts the lowest ``--occupied-layers``
height layers at opacity ~0.9 and the rest at ~1e-4, i.e. the ground and what stands on it are
solid and the air is clear, as in a trained model (Occ3D scenes are ~5-10 % occupied). Without
that, every Gaussian starts at the initial opacity 0.1 and pruning at 1/255 removes nothing.

Inputs: C = 6 cameras, images 256x704 (``--input``), LiDAR-like targets at ``--render`` (random
depth/labels on 40 % of pixels; the step's cost does not depend on their values), n015 calibration
(docs/formats.md#sensors-and-calibration). Each configuration runs in a fresh subprocess: median
wall time over ``--repeats`` steps after one warm-up, peak RSS growth over the process state after
set-up (CPU), or ``torch.cuda.max_memory_allocated`` (CUDA). The rasterizer is
``renderworld.splat.rasterize`` with ``--backend`` (default auto: gsplat on CUDA, the C++ kernel on
CPU when it builds, else the tiled torch backend); the backend used is printed.

Usage:
    PYTHONPATH=. python benchmarks/bench_img2occ.py [--grids coarse,occ3d] [--repeats 3]
        [--backend auto] [--views 3] [--threads 2] [--device cpu] [--depth-bins 40]
        [--precision 32|bf16|fp16] [--batch 1] [--prunes 0,1] [--profile-out FILE] [--dense-lift]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch
from steptime import run_point, time_steps

from renderworld.constants import CAMERA_NAMES, NUM_SEMANTIC_CLASSES, get_grid
from renderworld.geometry import pose_matrix
from renderworld.training.validation import autocast_context

# docs/formats.md#sensors-and-calibration (n015): translation, rotation [w, x, y, z], fx, cx, cy
# at 1600x900.
CALIB = (
    ((1.7008, 0.0160, 1.5110), (0.49980, -0.50303, 0.49978, -0.49737), 1266.4, 816.3, 491.5),
    ((1.5509, -0.4934, 1.4958), (0.20603, -0.20269, 0.68245, -0.67136), 1260.8, 808.0, 495.3),
    ((1.5239, 0.4946, 1.5093), (0.67573, -0.67363, 0.21214, -0.21123), 1272.6, 826.6, 479.8),
    ((0.0283, 0.0035, 1.5791), (0.50379, -0.49740, -0.49419, 0.50455), 809.2, 829.2, 481.8),
    ((1.0357, 0.4848, 1.5910), (0.69242, -0.70316, -0.11648, 0.11203), 1256.7, 792.1, 492.8),
    ((1.0149, -0.4806, 1.5624), (0.12281, -0.13240, -0.70043, 0.69050), 1259.5, 807.3, 501.2),
)


def _k(ci: int, w: int, h: int) -> np.ndarray:
    _, _, f, cx, cy = CALIB[ci]
    sx, sy = w / 1600.0, h / 900.0
    return np.array([[f * sx, 0, cx * sx], [0, f * sy, cy * sy], [0, 0, 1]])


def make_batch(input_hw, render_hw, device, seed=0, batch_size=1) -> dict:
    g = torch.Generator().manual_seed(seed)
    c, b = len(CAMERA_NAMES), batch_size
    (hi, wi), (hr, wr) = input_hw, render_hw
    depth = torch.rand(b, c, hr, wr, generator=g) * 50 + 1
    keep = torch.rand(b, c, hr, wr, generator=g) < 0.4
    sem = torch.randint(0, NUM_SEMANTIC_CLASSES, (b, c, hr, wr), generator=g)

    def rep(x: torch.Tensor) -> torch.Tensor:
        return x[None].expand(b, *x.shape).contiguous()

    batch = {
        "images": torch.rand(b, c, 3, hi, wi, generator=g),
        "intrinsics": rep(torch.tensor(np.stack([_k(i, wi, hi) for i in range(c)]))),
        "render_intrinsics": rep(torch.tensor(np.stack([_k(i, wr, hr) for i in range(c)]))),
        "cam_to_ego": rep(torch.tensor(np.stack([pose_matrix(t, q) for t, q, *_ in CALIB]))),
        "depth": torch.where(keep, depth, torch.zeros_like(depth)),
        "semantics": torch.where(keep, sem, torch.full_like(sem, 255)),
    }
    return {k: (v.float() if v.is_floating_point() else v).to(device) for k, v in batch.items()}


def _profile(step, device: torch.device, path: str, steps: int = 3) -> None:
    """Write ``torch.profiler``'s operator table of ``steps`` steps to ``path``: by device time
    (CUDA) or CPU time, plus the host's wall time per step, to see whether the device waits."""
    import time

    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    t0 = time.perf_counter()
    with profile(activities=acts) as prof:
        for _ in range(steps):
            step()
    wall = (time.perf_counter() - t0) / steps
    key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    table = prof.key_averages().table(sort_by=key, row_limit=25)
    with open(path, "w") as f:
        f.write(f"{steps} steps profiled, wall {wall * 1e3:.1f} ms a step (profiler on)\n{table}\n")


def run_one(args) -> dict:
    """One configuration, in this (fresh) process."""
    from renderworld.img2occ import Img2Occ, Img2OccConfig

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    grid = get_grid(args.grid)
    prune = 1.0 / 255.0 if args.prune else 0.0
    cfg = Img2OccConfig(
        grid=grid,
        input_size=tuple(args.input),
        render_size=tuple(args.render),
        views_per_step=args.views,
        prune_opacity=prune,
        render_backend=args.backend,
        depth_bins=args.depth_bins,
        lift_sparse=not args.dense_lift,
    )
    model = Img2Occ(cfg).to(device)
    z = grid.shape[2]
    with torch.no_grad():  # trained-like opacity field: solid bottom layers, clear air
        bias = model.head.out.bias.view(z, -1)
        bias[:, 10] = -9.0
        bias[: args.occupied_layers, 10] = 2.2
    batch = make_batch(cfg.input_size, cfg.render_size, device, batch_size=args.batch)
    opt = torch.optim.SGD(model.parameters(), lr=1e-6)
    model.train()

    def step():
        with autocast_context(args.precision, device):
            out = model(batch)
            loss, logs = model.loss(batch, out)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        return logs

    from renderworld.splat import available_backends

    backend = args.backend
    if backend == "auto":
        names = available_backends(device)
        backend = next(n for n in ("gsplat", "cpp", "torch") if n in names)
    timing = time_steps(lambda _i: step(), args.repeats, device)  # warm-up builds the C++ kernel
    logs = timing.warmup
    if args.profile_out:
        _profile(step, device, args.profile_out)
    return {
        "grid": args.grid,
        "anchors": grid.num_voxels,
        "prune": prune,
        "rendered": float(logs["gaussians_rendered"]),
        "backend": backend,
        "precision": args.precision,
        "batch": args.batch,
        "step_s": timing.step_s,
        "peak_mb": timing.peak_mb,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grids", default="coarse,occ3d")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--backend", default="auto")
    p.add_argument("--views", type=int, default=3, help="cameras rendered per step")
    p.add_argument("--input", type=int, nargs=2, default=(256, 704))
    p.add_argument("--render", type=int, nargs=2, default=(128, 352))
    p.add_argument("--occupied-layers", type=int, default=0, help="0: 1/8 of the height")
    p.add_argument(
        "--depth-bins", type=int, default=40, help="depth-aware lifting bins (0: mean lifting)"
    )
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--precision", default="32", choices=("32", "bf16", "fp16"), help="autocast")
    p.add_argument("--batch", type=int, default=1, help="samples per step")
    p.add_argument("--dense-lift", action="store_true", help="lift at every voxel (reference)")
    p.add_argument("--prunes", default="0,1", help="opacity pruning off (0) and/or on (1)")
    p.add_argument("--profile-out", default="", help="write the operator profile here (one point)")
    p.add_argument("--timeout", type=int, default=1800)
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--grid", default="coarse", help=argparse.SUPPRESS)
    p.add_argument("--prune", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        print(json.dumps(run_one(args)))
        return
    rows = []
    for grid in args.grids.split(","):
        layers = args.occupied_layers or max(1, get_grid(grid).shape[2] // 8)
        for prune in (int(x) for x in args.prunes.split(",")):
            cmd = [sys.executable, __file__, "--one", "--grid", grid, "--prune", str(prune)]
            cmd += ["--repeats", str(args.repeats), "--backend", args.backend]
            cmd += ["--views", str(args.views), "--threads", str(args.threads)]
            cmd += ["--input", *map(str, args.input), "--render", *map(str, args.render)]
            cmd += ["--occupied-layers", str(layers), "--device", args.device]
            cmd += ["--depth-bins", str(args.depth_bins), "--precision", args.precision]
            cmd += ["--batch", str(args.batch), "--profile-out", args.profile_out]
            cmd += ["--dense-lift"] if args.dense_lift else []
            row = run_point(cmd, f"{grid} prune={prune}", args.timeout)
            if row is not None:
                rows.append(row)
    print(
        f"\nImg2Occ training step (forward + loss + backward), 6 cameras at "
        f"{args.input[0]}x{args.input[1]}, {args.views} rendered at "
        f"{args.render[0]}x{args.render[1]}, batch {args.batch}, device {args.device}, "
        f"{args.threads} threads, depth bins {args.depth_bins}, precision {args.precision}, "
        f"lifting {'dense' if args.dense_lift else 'sparse'}"
    )
    print(f"{'grid':8} {'anchors':>8} {'pruning':>8} {'rendered':>9} {'backend':>8} "
          f"{'step ms':>8} {'steps/s':>8} {'peak MB':>9} {'vs unpruned':>12}")  # fmt: skip
    base = {}
    for r in rows:
        if r["prune"] == 0:
            base[r["grid"]] = r
    for r in rows:
        b = base.get(r["grid"])
        ratio = f"{r['step_s'] / b['step_s']:.2f}x t" if b and r is not b else ""
        print(
            f"{r['grid']:8} {r['anchors']:>8} {('1/255' if r['prune'] else 'off'):>8} "
            f"{int(r['rendered']):>9} {r['backend']:>8} {r['step_s'] * 1e3:>8.1f} "
            f"{1.0 / r['step_s']:>8.2f} {r['peak_mb']:>9.0f} {ratio:>12}"
        )


if __name__ == "__main__":
    main()
