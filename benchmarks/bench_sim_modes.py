"""Seconds per scene of the simulator's full and occupancy modes, same scenes, same run.

    PYTHONPATH=. python benchmarks/bench_sim_modes.py [--preset mini] [--num-scenes 2]
        [--repeats 3] [--keyframes N]

Simulates the preset's first ``--num-scenes`` scenes in ``mode=full`` and ``mode=occupancy``
(interleaved per repeat, so load drifts hit both alike) and prints the median seconds per scene
of each, their ratio, the bytes written and the median seconds per stage (per scene).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from renderworld.sim import simulate  # noqa: E402
from tools.make_fixtures import config_from_preset  # noqa: E402

MODES = ("full", "occupancy")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="mini")
    ap.add_argument("--num-scenes", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--keyframes", type=int, default=None, help="default: the preset's")
    args = ap.parse_args()
    over = {"num_scenes": args.num_scenes}
    if args.keyframes is not None:
        over["keyframes"] = args.keyframes
    runs: dict[str, list[dict]] = {m: [] for m in MODES}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            for mode in MODES:
                cfg = config_from_preset(args.preset, mode=mode, **over)
                runs[mode].append(simulate(cfg, Path(tmp) / f"{mode}-{rep}", progress=False))
    cfg = config_from_preset(args.preset, **over)
    n = len(cfg.scenes)
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    s = cfg.sensors
    size = f"{s.image_width}x{s.image_height}"
    print(f"simulator modes, preset={args.preset}: {n} scenes x {cfg.keyframes} keyframes, "
          f"{size} images, median of {args.repeats} (commit {commit})")  # fmt: skip
    per_scene = {m: statistics.median(r["seconds"] for r in runs[m]) / n for m in MODES}
    for m in MODES:
        r = runs[m][0]
        print(f"{m:>10s}: {per_scene[m]:7.2f} s per scene, {r['files']:5d} files, "
              f"{r['bytes'] / 2**20:7.1f} MiB")  # fmt: skip
    print(f"full / occupancy: {per_scene['full'] / per_scene['occupancy']:.2f}x")
    stages = sorted({k for m in MODES for r in runs[m] for k in r["stages"]})
    print(f"{'stage (s per scene)':24s} {'full':>8s} {'occupancy':>10s}")
    for st in stages:
        vals = [
            statistics.median(r["stages"].get(st, {"seconds": 0.0})["seconds"] for r in runs[m]) / n
            for m in MODES
        ]
        print(f"{st:24s} {vals[0]:8.3f} {vals[1]:10.3f}")


if __name__ == "__main__":
    main()
