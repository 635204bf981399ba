"""Converter and dataset throughput: keyframes/s for create_data, samples/s per dataset.

On a simulated dataset (``--preset tiny|mini``, made once with the simulator and cached under
``--root``) or an existing one (``--data DIR``). In one run, each timing the median of
``--repeat``:

* ``create_data`` from scratch (``overwrite=True``; infos + 2-D labels at the default scale),
  with ``workers=0`` and ``workers=2``, and a re-run with nothing to redo;
* ``Img2OccDataset`` at the default sizes (input 256x448, render = label size, coarse grid),
  without and with ``adjacent_frames=1``;
* ``OccSequenceDataset`` with the default 5 + 6 frames when scenes are long enough (else 2 + 6),
  with the frame cache on (default) and off, iterating windows in order.

Usage::

    python benchmarks/bench_converter.py [--preset mini] [--data DIR] [--repeat 3]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data_converters import ConvertOptions, create_data  # noqa: E402
from renderworld.data import Img2OccDataset, OccSequenceDataset, load_infos  # noqa: E402


def dataset(args) -> Path:
    """The dataset root: --data, or the simulator's preset (cached), or the test builder."""
    if args.data:
        return Path(args.data)
    root = Path(args.root) / args.preset
    if (root / args.version).is_dir():
        return root
    try:
        from renderworld.sim import simulate
        from tools.make_fixtures import config_from_preset

        simulate(config_from_preset(args.preset), root, progress=False)
    except ImportError:  # no simulator on this branch: the test builder (6 cameras, 2 scenes)
        from renderworld.constants import CAMERA_NAMES
        from tests.data.builder import build_tiny_dataset

        build_tiny_dataset(root, num_samples=12, num_points=34000, cameras=CAMERA_NAMES,
                           scene_names=("scene-0061", "scene-0103"), ego_path="left",
                           point_range=(2.0, 60.0))  # fmt: skip
    return root


def timed(fn, repeat: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def iterate(ds) -> int:
    for i in range(len(ds)):
        ds[i]
    return len(ds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="mini")
    ap.add_argument("--data", default=None, help="existing nuScenes-format dataset root")
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--root", default=str(REPO / ".cache" / "bench-converter"))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    root = dataset(args)
    out = Path(tempfile.mkdtemp(prefix="bench-converter-"))
    rows = []
    try:
        for workers in (0, 2):
            opts = ConvertOptions(progress=False, overwrite=True, workers=workers)
            sec, summary = timed(
                lambda o=opts: create_data(root, args.version, out, o), args.repeat
            )
            n = sum(summary.samples_per_split.values())
            rows.append((f"create_data workers={workers}", n, sec, n / sec, "keyframes/s"))
        quiet = ConvertOptions(progress=False)
        sec, _ = timed(lambda: create_data(root, args.version, out, quiet), args.repeat)
        rows.append(("create_data re-run (nothing to do)", n, sec, n / sec, "keyframes/s"))
        split = max(summary.samples_per_split, key=summary.samples_per_split.get)
        infos = load_infos(out, split)
        for adj in (0, 1):
            ds = Img2OccDataset(infos, root, adjacent_frames=adj)
            sec, count = timed(lambda d=ds: iterate(d), args.repeat)
            rows.append((f"Img2OccDataset adjacent_frames={adj}", count, sec, count / sec,
                         "samples/s"))  # fmt: skip
        longest = int(infos.groupby("scene_name").size().max())
        history = 5 if longest >= 11 else 2
        for cache in (32, 0):
            seq = OccSequenceDataset(infos, root, history=history, future=6, cache_frames=cache)
            sec, count = timed(lambda d=seq: iterate(d), args.repeat)
            rows.append((f"OccSequenceDataset {history}+6 cache={cache}", count, sec,
                         count / sec, "samples/s"))  # fmt: skip
        item = Img2OccDataset(infos, root)[0]
    finally:
        shutil.rmtree(out, ignore_errors=True)
    print(f"dataset: {root} ({args.version}), split {split!r}: {len(infos)} keyframes; "
          f"images {tuple(item['images'].shape)}, labels {tuple(item['depth'].shape)}; "
          f"median of {args.repeat}")  # fmt: skip
    print(f"{'what':42s} {'items':>6s} {'seconds':>9s} {'rate':>10s}")
    for name, count, sec, rate, unit in rows:
        print(f"{name:42s} {count:6d} {sec:9.3f} {rate:10.1f} {unit}")


if __name__ == "__main__":
    main()
