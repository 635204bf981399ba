"""Per-step and per-point cost of each kind of bench point, for ``renderworld/bench/estimate.py``.

Usage::

    PYTHONPATH=. python benchmarks/sweep_step_times.py [--steps 10 40] [--out DIR]
        [--data-root data/sim_mini] [--tokenizer-ckpt outputs/demo/tokenizer/checkpoints/best.pt]
        [--world-model-ckpt outputs/demo/world_model/checkpoints/best.pt]

Runs the default point of each training stage (the world model once per forecaster, Img2Occ
also on the quarter grid) at two step counts through the sweep's own path
(``renderworld.bench.run.run_sweep``: one subprocess per point, one torch thread, resumable
in ``--out``), and one planner point per grid; prints per kind the CPU seconds per step
(difference of the two runs' training CPU time over the difference of their steps), the CPU
seconds of the point besides its steps, and the same in wall seconds with the load average.
On a shared machine the wall figures grow with the others' load; a one-thread point's CPU
figures much less, and are what the estimate uses.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.bench.run import run_sweep  # noqa: E402
from renderworld.bench.sweep import expand_points  # noqa: E402

DEMO = Path("outputs/demo")
KINDS = {
    "tokenizer": ("tokenizer", "tokenizer_mini", []),
    "img2occ": ("img2occ", "img2occ_mini", ["stage.threshold.max_samples=24"]),
    "img2occ/quarter": (
        "img2occ",
        "img2occ_mini",
        ["stage.threshold.max_samples=24", "grid=quarter"],
    ),  # fmt: skip
    "world_model/pose_warp": ("world_model", "world_model_mini", []),
    "world_model/tokens": ("world_model", "world_model_mini", ["stage.forecaster=tokens"]),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, nargs=2, default=[10, 40])
    ap.add_argument("--out", type=Path, default=Path("outputs/bench/step_times"))
    ap.add_argument("--data-root", type=Path, default=Path("data/sim_mini"))
    ap.add_argument("--tokenizer-ckpt", type=Path, default=DEMO / "tokenizer/checkpoints/best.pt")
    ap.add_argument(
        "--world-model-ckpt", type=Path, default=DEMO / "world_model/checkpoints/best.pt"
    )
    ap.add_argument("--kinds", nargs="+", default=[*KINDS, "planner/mini", "planner/occ3d"])
    args = ap.parse_args()
    common = [f"dataset.data_root={args.data_root.resolve()}"]
    tok = f"{args.tokenizer_ckpt.resolve()}"
    print(f"# load average at start {os.getloadavg()[0]:.1f}", flush=True)
    rows = []
    for kind in args.kinds:
        if kind.startswith("planner/"):
            grid = kind.split("/")[1]
            preset = {"stages": {"planner": {"knobs": {"grid": [grid]}, "windows": 7}}}
            ups = {"planner": [f"tokenizer_ckpt={tok}",
                               f"world_model_ckpt={args.world_model_ckpt.resolve()}"]}  # fmt: skip
            pts = expand_points(preset, common=common, upstream=ups)
            pts = [p for p in pts if (p.knob == "default") == (grid == "mini")]
            (res,) = run_sweep(pts, args.out / kind.replace("/", "_"), infer_frames=7)
            rows.append((kind, float("nan"), res["point_cpu_s"], float("nan"),
                         res["point_wall_s"]))  # fmt: skip
            continue
        stage, experiment, overrides = KINDS[kind]
        results = []
        for steps in args.steps:
            spec = {"experiment": experiment, "budget": {"max_steps": steps, "max_minutes": None},
                    "seeds": [0], "overrides": overrides}  # fmt: skip
            ups = {"world_model": [f"stage.tokenizer_ckpt={tok}"]}
            pts = expand_points({"stages": {stage: spec}}, common=common, upstream=ups)
            out = args.out / f"{kind.replace('/', '_')}_{steps}"
            (res,) = run_sweep(pts, out, infer_frames=7)
            results.append(res)
        a, b = results
        steps = b["steps"] - a["steps"]
        cpu_step = (b["train_cpu_s"] - a["train_cpu_s"]) / steps
        wall_step = (b["train_s"] - a["train_s"]) / steps
        rows.append((kind, cpu_step, b["point_cpu_s"] - cpu_step * b["steps"], wall_step,
                     b["point_wall_s"] - wall_step * b["steps"]))  # fmt: skip
    print(f"# load average at end {os.getloadavg()[0]:.1f}")
    print(f"{'kind':<24}{'cpu s/step':>11}{'cpu s/point':>12}{'wall s/step':>12}"
          f"{'wall s/point':>13}")  # fmt: skip
    for kind, cs, cp, ws, wp in rows:
        print(f"{kind:<24}{cs:>11.3f}{cp:>12.1f}{ws:>12.3f}{wp:>13.1f}")


if __name__ == "__main__":
    main()
