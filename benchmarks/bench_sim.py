"""Per-effect cost of the simulator: a static scene vs a busy one, measured in the same run.

    PYTHONPATH=. python benchmarks/bench_sim.py [--keyframes 6] [--repeats 3] [--size 400x225]

The static scene has no moving agents, a parked ego, no noise and clear daylight; the busy
scene has a moving ego, traffic and pedestrians, LiDAR and camera noise, fog and night. Both
use the same road kind, keyframes and image size. Prints medians over repeats (seconds per
keyframe) per stage and per effect, and the busy/static ratio.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from renderworld.sim import EffectsSpec, SceneSpec, SimConfig, simulate


def scene_config(busy: bool, keyframes: int, size: tuple[int, int]) -> SimConfig:
    if busy:
        effects = EffectsSpec(weather="fog", night=True)
        spec = SceneSpec(kind="intersection", behaviour="turn_left", num_moving=12,
                         num_pedestrians=12, effects=effects)  # fmt: skip
    else:
        spec = SceneSpec(kind="intersection", behaviour="parked", num_moving=0, num_pedestrians=0,
                         effects=EffectsSpec(ego_motion=False, agent_motion=False,
                                             lidar_noise=False, camera_noise=False))  # fmt: skip
    cfg = SimConfig(keyframes=keyframes, scenes=[spec], scene_names=["scene-0061"])
    cfg.sensors.image_width, cfg.sensors.image_height = size
    return cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--size", default="400x225")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    results: dict[str, list[dict]] = {"static": [], "busy": []}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            for name in ("static", "busy"):  # interleaved so load drifts hit both alike
                cfg = scene_config(name == "busy", args.keyframes, size)
                out = Path(tmp) / f"{name}-{rep}"
                results[name].append(simulate(cfg, out, progress=False))
    k = args.keyframes
    print(f"simulator cost, 1 scene x {k} keyframes, {size[0]}x{size[1]} images, "
          f"median of {args.repeats} (ms per keyframe)")  # fmt: skip
    rows = [("total", "seconds")]
    stages = sorted({s for r in results["busy"] + results["static"] for s in r["stages"]})
    rows += [(f"stage:{s}", s) for s in stages]
    rows += [(f"effect:{e}", e) for e in results["busy"][0]["effects"]]
    print(f"{'':24s} {'static':>10s} {'busy':>10s} {'busy/static':>12s}")
    for label, key in rows:
        vals = {}
        for name, reps in results.items():
            if key == "seconds":
                xs = [r["seconds"] for r in reps]
            elif label.startswith("stage:"):
                xs = [r["stages"].get(key, {"seconds": 0.0})["seconds"] for r in reps]
            else:
                xs = [r["effects"][key]["seconds"] for r in reps]
            vals[name] = 1000 * statistics.median(xs) / k
        ratio = vals["busy"] / vals["static"] if vals["static"] > 0 else float("inf")
        ran = ""
        if label.startswith("effect:"):
            flags = ["yes" if results[n][0]["effects"][key]["ran"] else "no" for n in results]
            ran = f"  ran: static={flags[0]} busy={flags[1]}"
        ratio_s = f"{ratio:12.2f}" if vals["static"] > 0 else f"{'-':>12s}"
        print(f"{label:24s} {vals['static']:10.1f} {vals['busy']:10.1f} {ratio_s}{ran}")


if __name__ == "__main__":
    main()
