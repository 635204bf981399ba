"""World-model data benchmark: a window's load time without and with the on-disk frame cache.

For every window of a split, in the same run, times ``WorldModelWindows[i]`` (eleven frames by
default) three ways: no frame cache (read ``labels.npz``, zlib, down-sample), the cache cold
(the same plus writing each entry) and warm (entries read back). The in-memory LRU is off
(``cache_frames=0``) so every frame goes to its source, as with shuffled windows. Prints the
median milliseconds per window and the ratio to no cache.

Usage::

    python benchmarks/bench_frame_cache.py --data-root data/sim_mini [--split train]
        [--grid coarse] [--repeat 3]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderworld.data import load_infos  # noqa: E402
from renderworld.training.stages.world_model.windows import WorldModelWindows  # noqa: E402


def _per_window_ms(ds) -> float:
    times = []
    for i in range(len(ds)):
        t = time.perf_counter()
        ds[i]
        times.append(1e3 * (time.perf_counter() - t))
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-root", required=True)
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--split", default="train")
    ap.add_argument("--grid", default="coarse")
    ap.add_argument("--history", type=int, default=5)
    ap.add_argument("--future", type=int, default=6)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    root = Path(args.data_root)
    infos = load_infos(root / "renderworld_infos" / args.version, args.split)
    tmp = Path(tempfile.mkdtemp(prefix="frame-cache-bench-"))
    try:

        def windows(cache):
            ds = WorldModelWindows(infos, root, args.grid, args.history, args.future,
                                   frame_cache=cache)  # fmt: skip
            ds.seq.cache_frames = 0
            return ds

        plain = [_per_window_ms(windows(None)) for _ in range(args.repeat)]
        cold = []
        for r in range(args.repeat):
            cold.append(_per_window_ms(windows(tmp / f"c{r}")))
        warm = [_per_window_ms(windows(tmp / "c0")) for _ in range(args.repeat)]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    n = len(windows(None))
    base = statistics.median(plain)
    print(f"{n} windows of {args.history + args.future} frames, split {args.split}, grid "
          f"{args.grid}; median ms per window over {args.repeat} passes")  # fmt: skip
    for name, vals in (("no cache", plain), ("cache cold", cold), ("cache warm", warm)):
        med = statistics.median(vals)
        print(f"{name:<11} {med:8.2f} ms   x{base / med:5.2f} vs no cache")


if __name__ == "__main__":
    main()
