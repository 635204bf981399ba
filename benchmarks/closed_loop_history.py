"""What a planner reads in closed loop: per plan, the history's heading changes and step lengths.

Drives the interaction split (``tools/drive.py``'s worlds) with one planner and prints, for the
last ``--last`` plans of each scene, the keyframe, the command, the heading change of each history
step (degrees), each step's length (metres) and where the plan ends at 3 s (x forward, y left,
metres). Logged histories on a straight road hold heading changes of zero; a plan that turns a
little makes the next history turn a little, which the planner may read as a turn starting.

Usage::

    python benchmarks/closed_loop_history.py outputs/demo/planner/planner.pt \\
        [--scenes 16] [--last 4]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from renderworld.sim import build_worlds  # noqa: E402
from renderworld.sim.closed_loop.episode import run_episode  # noqa: E402
from renderworld.sim.closed_loop.planners import make_planner  # noqa: E402
from tools.make_fixtures import config_from_preset  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "planner", help="a planner bundle (tools/export_planner.py) or a reference name"
    )
    ap.add_argument("--preset", default="interactions")
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--last", type=int, default=4, help="plans printed per scene (its last ones)")
    args = ap.parse_args()
    planner = make_planner(args.planner)
    inner = planner.plan
    rows: list[str] = []

    def plan(obs):
        traj = inner(obs)
        dyaw = np.rad2deg(np.diff(np.asarray(obs.yaws, dtype=np.float64)))
        steps = np.linalg.norm(np.asarray(obs.displacements, dtype=np.float64), axis=-1)
        rows.append(
            f"  keyframe {obs.keyframe:2d} {obs.command:8s} heading changes "
            f"{np.array2string(dyaw, precision=2, floatmode='fixed')} deg, steps "
            f"{np.array2string(steps, precision=2, floatmode='fixed')} m, plan at 3 s "
            f"({traj[-1][0]:.1f}, {traj[-1][1]:.1f}) m"
        )
        return traj

    planner.plan = plan
    for world in build_worlds(config_from_preset(args.preset))[: args.scenes]:
        rows.clear()
        run_episode(world, planner)
        print(world.name)
        print("\n".join(rows[-args.last :]))


if __name__ == "__main__":
    main()
