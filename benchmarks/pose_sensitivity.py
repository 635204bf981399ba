"""How much a pose error costs the GT-pose warp: forecast mIoU with perturbed future poses.

Scores, on a converted fixture's val windows, the current frame warped along the ground-truth
future poses (the reference row of the world-model table), then the same with the heading
offset by 1 / 2 / 4 degrees or the position by 0.5 / 1 / 2 m, and with CTR headings or CTR
positions swapped in. Prints mIoU at 1 / 2 / 3 s (percent).

Usage::

    python benchmarks/pose_sensitivity.py --data-root data/sim_mini [--split val]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.constants import GRIDS  # noqa: E402
from renderworld.data import load_infos  # noqa: E402
from renderworld.metrics import ForecastMetric  # noqa: E402
from renderworld.training.stages.world_model.windows import WorldModelWindows  # noqa: E402
from renderworld.world import constant_turn_rate_poses, warp_along_poses  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-root", required=True)
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--split", default="val")
    args = ap.parse_args()
    grid = GRIDS["coarse"]
    root = Path(args.data_root)
    infos = load_infos(root / "renderworld_infos" / args.version, args.split)
    ds = WorldModelWindows(infos, root, grid, 5, 6)
    items = [ds[i] for i in range(len(ds))]

    def score(poses_of) -> list[float]:
        m = ForecastMetric(6, (1.0, 2.0, 3.0))
        for it in items:
            m.update(warp_along_poses(it["occ"][4], poses_of(it), grid), it["occ"][5:])
        r = m.compute()
        return [round(100 * r[f"miou@{h}s"], 1) for h in (1, 2, 3)]

    def gt(it):
        return it["future_poses"].double()

    def ctr(it):
        return constant_turn_rate_poses(it["history_poses"].double(), 6)

    def mix(xy, yaw):
        return lambda it: torch.cat([xy(it)[:, :2], yaw(it)[:, 2:]], 1)

    rows = [
        ("GT poses", gt),
        ("GT positions, CTR headings", mix(gt, ctr)),
        ("CTR positions, GT headings", mix(ctr, gt)),
    ]
    for deg in (1, 2, 4):
        off = torch.tensor([0.0, 0.0, np.radians(deg)], dtype=torch.float64)
        rows.append((f"GT, heading +{deg} deg", lambda it, o=off: gt(it) + o))
    for m in (0.5, 1.0, 2.0):
        off = torch.tensor([m, 0.0, 0.0], dtype=torch.float64)
        rows.append((f"GT, x +{m} m", lambda it, o=off: gt(it) + o))
    print(f"{len(items)} {args.split} windows of {root}; grid coarse; mIoU 1 / 2 / 3 s (%)")
    for name, fn in rows:
        print(f"{name:<28} {' / '.join(f'{v:.1f}' for v in score(fn))}")


if __name__ == "__main__":
    main()
