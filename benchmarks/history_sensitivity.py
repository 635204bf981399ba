"""How far the learned plan moves for a few centimetres of its own history.

In closed loop the ego's history is what the last plans made of it, and a pose head that reads
centimetre changes of its step lengths (``renderworld.world.pose_inputs.kinematic_features``)
takes a plan driven a few centimetres short for the ego starting to brake: each slower plan,
driven, slows the next one (``docs/world_model.md``, "Noise on the pose head's history"). For
every window of a fixture this plans once from the logged history and once each with the last
history step ``--delta-m`` shorter and longer along its direction (the earlier steps kept), the
trajectory only (``forecast=False``, no check), and prints how far the 3 s waypoint moves along
the ego's heading: the median and the mean absolute change per perturbation, the gain (mean
absolute change over the perturbation) and the same per speed band.

Score development splits with it (``docs/protocol.md``).

Usage::

    python benchmarks/history_sensitivity.py --bundle outputs/demo/planner/planner.pt \\
        --data-root data/sim_dev --split all [--delta-m 0.03] [--out FILE.csv]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.constants import COMMANDS, KEYFRAME_DT  # noqa: E402

#: Speed bands of the summary, m/s (the last step's speed): [low, high).
BANDS = ((0.0, 5.0), (5.0, 10.0), (10.0, np.inf))


def perturbed_last_step(displacements: np.ndarray, delta_m: float) -> np.ndarray:
    """[H-1, 2] the per-step displacements with the last one ``delta_m`` longer (negative:
    shorter) along its own direction; a step shorter than 1 mm is left as it is.

    Args:
        displacements: [H-1, 2] metres, ``d[i] = p[i+1] - p[i]``, current ego frame.
        delta_m: metres.
    """
    d = np.array(displacements, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 2 or len(d) < 1:
        raise ValueError(f"displacements: expected [H-1 >= 1, 2], got {d.shape}")
    n = float(np.hypot(*d[-1]))
    if n >= 1e-3:
        d[-1] *= (n + delta_m) / n
    return d


def summary(rows: list[dict], delta_m: float) -> str:
    """A markdown table of the 3 s waypoint's change (metres, along the ego's heading) per
    perturbation and speed band: windows, median, mean absolute and gain (mean absolute over
    ``delta_m``).

    Args:
        rows: per window ``{"speed": m/s, "shorter": m, "longer": m}`` (the changes).
        delta_m: the perturbation, metres.
    """
    lines = [
        f"| speed band (m/s) | windows | {delta_m * 100:g} cm shorter: median; mean abs.; gain "
        f"| {delta_m * 100:g} cm longer: median; mean abs.; gain |",
        "|---|---|---|---|",
    ]
    for lo, hi in ((0.0, np.inf), *BANDS):
        sel = [r for r in rows if lo <= r["speed"] < hi]
        if not sel:
            continue
        name = "all" if (lo, hi) == (0.0, np.inf) else f"{lo:g}-{hi:g}"
        cells = []
        for key in ("shorter", "longer"):
            v = np.array([r[key] for r in sel])
            mean_abs = float(np.abs(v).mean())
            cells.append(f"{np.median(v):+.3f} m; {mean_abs:.3f} m; {mean_abs / delta_m:.1f}x")
        lines.append(f"| {name} | {len(sel)} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)


def main() -> None:
    from renderworld.data import load_infos
    from renderworld.planning import PlanRequest, load_planner
    from renderworld.training.stages.world_model.windows import WorldModelWindows

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True, help="a planner bundle (planner.pt)")
    ap.add_argument("--data-root", type=Path, required=True)
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--split", default="all")
    ap.add_argument("--delta-m", type=float, default=0.03)
    ap.add_argument("--out", type=Path, default=None, help="per-window CSV")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    if not args.delta_m > 0:
        raise SystemExit(f"--delta-m: expected a length > 0 (metres), got {args.delta_m}")
    if not args.bundle.is_file():
        raise SystemExit(f"--bundle: no planner bundle at {args.bundle}")
    torch.set_num_threads(args.threads)
    planner = load_planner(args.bundle)
    if planner.kind != "pose_warp":
        raise SystemExit(f"--bundle: a pose-warp world model is needed, got {planner.kind!r}")
    h, grid = planner.config.history_frames, planner.grid
    infos = load_infos(args.data_root / "renderworld_infos" / args.version, args.split)
    windows = WorldModelWindows(infos, args.data_root, grid, h, planner.config.future_frames)
    rows = []
    for i in range(len(windows)):
        it = windows[i]
        poses = it["history_poses"].double().numpy()
        occ, cmd = it["occ"][:h].numpy(), COMMANDS[int(it["command"])]
        disp = np.diff(poses[:, :2], axis=0)
        plans = planner.plan_batch(
            [PlanRequest(occ, d, cmd, ego_yaws=poses[:, 2])
             for d in (disp, perturbed_last_step(disp, -args.delta_m),
                       perturbed_last_step(disp, args.delta_m))],
            forecast=False,
        )  # fmt: skip
        x3 = [float(p.trajectory[-1, 0]) for p in plans]
        rows.append({
            "scene": it["meta"]["scene"],
            "speed": float(np.hypot(*disp[-1]) / KEYFRAME_DT),
            "x3": x3[0], "shorter": x3[1] - x3[0], "longer": x3[2] - x3[0],
        })  # fmt: skip
    print(f"{args.bundle}: {len(rows)} windows of {args.data_root} ({args.split}); the 3 s "
          f"waypoint's change along the heading for the last history step changed by "
          f"{args.delta_m:g} m")  # fmt: skip
    print(summary(rows, args.delta_m))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"per window: {args.out}")


if __name__ == "__main__":
    main()
