"""Benchmark the Gaussian rasterizer backends on a voxel-anchored driving scene.

Scene: N Gaussians at a random subset of Occ3D voxel centres ([-40, 40]² x [-1, 5.4] m at 0.4 m,
ego frame), denser near the ground (z level k drawn with weight exp(-k / 4)), voxels inside the ego
car left out; scales uniform in [0.1, 0.3] m, random rotations, opacities uniform in [0.05, 0.95],
17 feature channels (the semantic classes). N = 640k is every voxel of the grid.

Cameras: the six nuScenes cameras with the n015 calibration
(docs/formats.md#sensors-and-calibration), world = ego frame.
Intrinsics follow the BEVDet-style resize-then-crop: scale the 1600 x 900 image by W / 1600
(176 -> 176 x 99, 704 -> 704 x 396) and crop the top rows (sky) to H (96 or 256), i.e.
fx, fy, cx scale by s and cy becomes s·cy - (round(900 s) - H).

Per configuration (backend, N, H x W), in a fresh subprocess: median wall time of the forward
(inputs requiring grad, as in training) and of forward + backward (loss = sum of all outputs),
after one warm-up, and the process CPU time of the same calls (all threads; a load-independent
figure on a shared machine); peak memory as the growth of the process' max RSS over its state
after set-up (forward alone, then forward + backward); tile–Gaussian intersections and the
pixel–Gaussian pairs they stand for (intersections x tile pixels, what a 16-px tiled rasterizer
considers); forward pairs/s against the machine's torch.exp throughput measured in the same
run (float32, same thread count), and speed ratios against the dense reference where it ran.

Usage:
    PYTHONPATH=. python benchmarks/bench_splat.py [--quick] [--out results.csv]
        [--backends cpp,torch,reference] [--repeats 5] [--threads 2]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

from renderworld.constants import CAMERA_NAMES, NUM_SEMANTIC_CLASSES, OCC3D_GRID
from renderworld.geometry import invert_pose, pose_matrix

# Vehicle n015 (docs/formats.md#sensors-and-calibration): sensor->ego translation (m), rotation
# (w, x, y, z), fx = fy, cx, cy at 1600 x 900.
CALIBRATION = {
    "CAM_FRONT": (
        [1.7008, 0.0160, 1.5110],
        [0.49980, -0.50303, 0.49978, -0.49737],
        (1266.4, 816.3, 491.5),
    ),
    "CAM_FRONT_RIGHT": (
        [1.5509, -0.4934, 1.4958],
        [0.20603, -0.20269, 0.68245, -0.67136],
        (1260.8, 808.0, 495.3),
    ),
    "CAM_FRONT_LEFT": (
        [1.5239, 0.4946, 1.5093],
        [0.67573, -0.67363, 0.21214, -0.21123],
        (1272.6, 826.6, 479.8),
    ),
    "CAM_BACK": (
        [0.0283, 0.0035, 1.5791],
        [0.50379, -0.49740, -0.49419, 0.50455],
        (809.2, 829.2, 481.8),
    ),
    "CAM_BACK_LEFT": (
        [1.0357, 0.4848, 1.5910],
        [0.69242, -0.70316, -0.11648, 0.11203],
        (1256.7, 792.1, 492.8),
    ),
    "CAM_BACK_RIGHT": (
        [1.0149, -0.4806, 1.5624],
        [0.12281, -0.13240, -0.70043, 0.69050],
        (1259.5, 807.3, 501.2),
    ),
}
FULL_W, FULL_H = 1600, 900
SIZES = [(96, 176), (256, 704)]
NUMS = [1_000, 10_000, 80_000, 640_000]
# Largest N per (backend, size) that is run; bigger ones are reported as skipped.
LIMITS = {
    ("reference", (96, 176)): 10_000,
    ("reference", (256, 704)): 1_000,
    ("torch", (96, 176)): 80_000,
    ("torch", (256, 704)): 10_000,
}


def cameras(height: int, width: int, dtype=torch.float32):
    """Six nuScenes cameras for an H x W render: ``(viewmats [6, 4, 4], Ks [6, 3, 3])``."""
    s = width / FULL_W
    crop_top = round(FULL_H * s) - height
    if crop_top < 0:
        raise ValueError(f"height: at most {round(FULL_H * s)} for width {width}, got {height}")
    viewmats, ks = [], []
    for name in CAMERA_NAMES:
        t, q, (f, cx, cy) = CALIBRATION[name]
        viewmats.append(invert_pose(pose_matrix(t, q)))
        ks.append([[f * s, 0.0, cx * s], [0.0, f * s, cy * s - crop_top], [0.0, 0.0, 1.0]])
    return torch.tensor(np.array(viewmats), dtype=dtype), torch.tensor(ks, dtype=dtype)


def voxel_scene(n: int, seed: int = 0, dtype=torch.float32):
    """N Gaussians at Occ3D voxel centres (see module docstring): the five rasterizer inputs."""
    g = torch.Generator().manual_seed(seed)
    nx, ny, nz = OCC3D_GRID.shape
    lo = torch.tensor(OCC3D_GRID.range_min, dtype=torch.float64)
    size = torch.tensor(OCC3D_GRID.voxel_size, dtype=torch.float64)
    ix, iy, iz = torch.meshgrid(torch.arange(nx), torch.arange(ny), torch.arange(nz), indexing="ij")
    idx = torch.stack([ix, iy, iz], -1).reshape(-1, 3)
    centres = lo + (idx + 0.5) * size
    in_car = (centres[:, 0].abs() < 2.6) & (centres[:, 1].abs() < 1.0) & (centres[:, 2] < 2.0)
    weights = torch.exp(-idx[:, 2].double() / 4.0) * (~in_car)
    n = min(n, int((weights > 0).sum()))
    pick = torch.multinomial(weights, n, replacement=False, generator=g)
    means = centres[pick].to(dtype)
    quats = torch.randn(n, 4, generator=g).to(dtype)
    scales = (0.1 + 0.2 * torch.rand(n, 3, generator=g)).to(dtype)
    opacities = (0.05 + 0.9 * torch.rand(n, generator=g)).to(dtype)
    features = torch.randn(n, NUM_SEMANTIC_CLASSES, generator=g).to(dtype)
    return [means, quats, scales, opacities, features]


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def exp_ceiling(repeats: int = 5) -> float:
    """Median torch.exp throughput (float32 elements per second) on 2^24 elements."""
    x = -torch.rand(1 << 24)
    out = torch.empty_like(x)
    torch.exp(x, out=out)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.exp(x, out=out)
        times.append(time.perf_counter() - t0)
    return x.numel() / statistics.median(times)


def run_child(backend: str, n: int, height: int, width: int, repeats: int) -> dict:
    """One configuration, measured in this (fresh) process."""
    from renderworld.splat import rasterize
    from renderworld.splat.binning import bin_gaussians
    from renderworld.splat.projection import project_gaussians

    params = voxel_scene(n)
    viewmats, ks = cameras(height, width)
    leaves = [p.clone().requires_grad_(True) for p in params]
    with torch.no_grad():
        proj = project_gaussians(*params[:4], viewmats, ks, width, height, 0.01, 1e10)
        bins = bin_gaussians(proj, viewmats.shape[0], width, height, 16)
    isect = int(bins.pair_ids.numel())
    if backend == "cpp":
        from renderworld.splat.cpp_backend import cpp_available

        if not cpp_available():
            return {"status": "cpp kernel unavailable"}

    def forward():
        return rasterize(*leaves, viewmats, ks, width, height, backend=backend)

    def forward_backward():
        r = forward()
        (r.features.sum() + r.depth.sum() + r.alpha.sum()).backward()
        for p in leaves:
            p.grad = None
        return r

    base = _maxrss_mb()
    forward()  # warm-up (and the forward peak)
    fwd, fwd_cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        r = forward()
        fwd.append(time.perf_counter() - t0)
        fwd_cpu.append(time.process_time() - c0)
        del r
    fwd_peak = _maxrss_mb() - base
    forward_backward()
    both, both_cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        forward_backward()
        both.append(time.perf_counter() - t0)
        both_cpu.append(time.process_time() - c0)
    return {
        "status": "ok",
        "visible_pairs": len(proj),
        "isect": isect,
        "pairs": isect * 16 * 16,
        "fwd_s": statistics.median(fwd),
        "fwdbwd_s": statistics.median(both),
        "fwd_cpu_s": statistics.median(fwd_cpu),
        "fwdbwd_cpu_s": statistics.median(both_cpu),
        "fwd_peak_mb": fwd_peak,
        "fwdbwd_peak_mb": _maxrss_mb() - base,
    }


def spawn(backend, n, height, width, repeats, threads, timeout) -> dict:
    cmd = [sys.executable, __file__, "--child", json.dumps([backend, n, height, width, repeats])]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    env["PYTHONPATH"] = os.pathsep.join([os.getcwd(), env.get("PYTHONPATH", "")])
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {"status": f"timeout > {timeout} s"}
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode != 0 or not lines:
        return {"status": f"failed: {res.stderr.strip().splitlines()[-1:]}"}
    return json.loads(lines[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="N in {1k, 10k}, 96x176 only, 3 repeats")
    ap.add_argument("--out", help="write the table as CSV here")
    ap.add_argument("--backends", default="cpp,torch,reference")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per configuration")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", torch.get_num_threads())))
        print(json.dumps(run_child(*json.loads(args.child))))
        return

    torch.set_num_threads(args.threads)
    nums, sizes, repeats = NUMS, SIZES, args.repeats
    if args.quick:
        nums, sizes, repeats = NUMS[:2], SIZES[:1], 3
    backends = args.backends.split(",")
    load = os.getloadavg()
    ceiling = exp_ceiling()
    print(f"threads={args.threads}  load average={load[0]:.2f}/{load[1]:.2f}/{load[2]:.2f}  "
          f"torch.exp ceiling={ceiling / 1e9:.3f} G elem/s (float32)")  # fmt: skip
    rows = []
    for height, width in sizes:
        for n in nums:
            results = {}
            for backend in backends:
                limit = LIMITS.get((backend, (height, width)), max(NUMS))
                if n > limit:
                    results[backend] = {"status": f"skipped (N > {limit})"}
                    continue
                reps = 1 if backend == "reference" else repeats
                results[backend] = spawn(
                    backend, n, height, width, reps, args.threads, args.timeout
                )
            ref = results.get("reference", {})
            for backend, res in results.items():
                row = {"backend": backend, "N": n, "H": height, "W": width, **res}
                if res.get("status") == "ok":
                    row["fwd_pairs_per_s"] = res["pairs"] / res["fwd_s"]
                    row["fwd_vs_exp"] = row["fwd_pairs_per_s"] / ceiling
                    if ref.get("status") == "ok" and backend != "reference":
                        row["fwd_speedup_vs_ref"] = ref["fwd_s"] / res["fwd_s"]
                        row["fwdbwd_speedup_vs_ref"] = ref["fwdbwd_s"] / res["fwdbwd_s"]
                rows.append(row)
                _print_row(row)
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")
    if args.out:
        keys = sorted(
            {k for r in rows for k in r},
            key=lambda k: list(rows[0]).index(k) if k in rows[0] else 99,
        )
        with open(args.out, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=keys)
            writer.writeheader()
            writer.writerows(rows)
        print(f"wrote {args.out}")


def _print_row(row: dict) -> None:
    head = f"{row['backend']:>9} N={row['N']:>7} {row['H']}x{row['W']:<4}"
    if row.get("status") != "ok":
        print(f"{head} {row.get('status')}")
        return
    text = (
        f"{head} fwd {row['fwd_s'] * 1e3:8.1f} ms  fwd+bwd {row['fwdbwd_s'] * 1e3:8.1f} ms "
        f"(cpu {row['fwdbwd_cpu_s'] * 1e3:8.1f} ms)  "
        f"peak +{row['fwd_peak_mb']:7.0f}/{row['fwdbwd_peak_mb']:7.0f} MB  "
        f"isect {row['isect']:>9}  pairs/s {row['fwd_pairs_per_s'] / 1e6:8.1f} M "
        f"({100 * row['fwd_vs_exp']:5.1f}% of exp)"
    )
    if "fwd_speedup_vs_ref" in row:
        text += f"  vs ref x{row['fwd_speedup_vs_ref']:.1f} fwd"
        text += f", x{row['fwdbwd_speedup_vs_ref']:.1f} fwd+bwd"
    print(text, flush=True)


if __name__ == "__main__":
    main()
