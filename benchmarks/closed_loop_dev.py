"""The four closed-loop development sets, driven and summed up in one command.

Drives a planner bundle's checked plan (``tools/drive.py ... 'planners=[]' planner=<bundle>``,
one thread per drive) on the sets `docs/protocol.md` names, none of them a test split:

* ``turns``: the scenario library's 16 turn scenes;
* ``routes``: its cruise, stop-and-go, lane-change and parked scenes (26);
* ``pdev`` (planner dev): its first 50 interaction scenes;
* ``pdevi`` (planner dev, interactions): the dev-interactions worlds, 64 (seed 1002).

Each set's run lands in ``<out>/<set>/`` (``closed_loop.csv`` and ``.md``). Prints one row per
set (PDMS, scenes with an at-fault contact, comfort failures, EP, TTC) and the mean over all
scenes, the figure the planner's knobs are chosen by. With ``--against <dir>`` (an earlier
run of this script) each set is also paired scene by scene with it
(:mod:`renderworld.sim.closed_loop.compare`). A set whose ``closed_loop.csv`` is already there is
not driven again (``--redo`` drives it anyway), so an interrupted run resumes.

Usage::

    python benchmarks/closed_loop_dev.py --bundle outputs/demo/planner/planner.pt \\
        --out outputs/dev_loop/base
    python benchmarks/closed_loop_dev.py --bundle outputs/demo/planner/planner.pt \\
        --check '{change_cost: 0.1}' --out outputs/dev_loop/cost01 --against outputs/dev_loop/base
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from renderworld.sim.closed_loop.compare import compare_runs, load_run  # noqa: E402

#: The development sets: name -> ``tools/drive.py`` arguments (docs/protocol.md).
SETS = {
    "turns": ["preset=scenarios", "behaviours=[turn_left,turn_right]"],
    "routes": ["preset=scenarios", "behaviours=[cruise,stop_and_go,lane_change_left,parked]"],
    "pdev": ["preset=scenarios", "behaviours=interactions", "max_scenes=50"],
    "pdevi": ["preset=interactions", "seed=1002", "num_scenes=64"],
}
PLANNER = "world_model"


def drive(name: str, bundle: Path, out: Path, check: str | None, redo: bool) -> Path:
    """Drive one set (skipped where its table is already there); returns its run directory.

    Raises:
        RuntimeError: naming the set and its log when ``tools/drive.py`` fails.
    """
    run = out / name
    if (run / "closed_loop.csv").is_file() and not redo:
        return run
    cmd = [sys.executable, str(ROOT / "tools" / "drive.py"), *SETS[name], "planners=[]",
           f"planner={bundle}", "threads=1", f"out={run}"]  # fmt: skip
    if check:
        cmd.append(f"check={check}")
    out.mkdir(parents=True, exist_ok=True)
    log = out / f"{name}.log"
    with open(log, "w") as f:
        rc = subprocess.run(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise RuntimeError(f"set {name}: tools/drive.py failed with exit code {rc}; see {log}")
    return run


def summary(rows: pd.DataFrame) -> dict:
    """Scores of a planner's rows (:func:`~renderworld.sim.closed_loop.compare.load_run`): mean
    PDMS, EP and TTC, and the scenes with an at-fault contact and with comfort lost."""
    return {
        "scenes": len(rows),
        "PDMS": float(rows["PDMS"].mean()),
        "at_fault": int(rows["at_fault_collision"].astype(bool).sum()),
        "comfort_fails": int((rows["C"] < 1).sum()),
        "EP": float(rows["EP"].mean()),
        "TTC": float(rows["TTC"].mean()),
    }


def table(runs: dict[str, pd.DataFrame], against: dict[str, pd.DataFrame] | None) -> str:
    """Markdown: one row per set and the mean over all their scenes; with ``against``, the
    paired PDMS difference (± its standard error) of each set and of all."""
    head = "| set | scenes | PDMS | at fault | comfort fails | EP | TTC |"
    rule = "|---|---|---|---|---|---|---|"
    if against:
        head, rule = head + " vs --against (± s.e.) |", rule + "---|"
    lines = [head, rule]
    every = {"all": _pooled(runs)}
    base_every = {"all": _pooled(against)} if against else {}
    for name, rows in [*runs.items(), *every.items()]:
        s = summary(rows)
        line = (f"| {name} | {s['scenes']} | {s['PDMS']:.3f} | {s['at_fault']} | "
                f"{s['comfort_fails']} | {s['EP']:.3f} | {s['TTC']:.3f} |")  # fmt: skip
        if against:
            base = {**against, **base_every}[name]
            o = compare_runs(base, rows)["overall"]
            line += f" {o['PDMS_b'] - o['PDMS_a']:+.3f} ± {o['PDMS_se']:.3f} |"
        lines.append(line)
    return "\n".join(lines)


def _pooled(runs: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Every set's rows in one frame, each scene named ``<set>/<scene>`` (the sets are
    different worlds: a scene name may recur)."""
    frames = [rows.set_axis([f"{name}/{s}" for s in rows.index]) for name, rows in runs.items()]
    out = pd.concat(frames)
    out.attrs = {}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, required=True, help="planner bundle (.pt)")
    ap.add_argument("--out", type=Path, required=True, help="run directory (one folder per set)")
    ap.add_argument("--check", help="CheckConfig overrides, as tools/drive.py's check={...}")
    ap.add_argument("--sets", nargs="+", default=list(SETS), choices=list(SETS))
    ap.add_argument("--against", type=Path, help="an earlier run of this script to pair with")
    ap.add_argument("--jobs", type=int, default=2, help="sets driven at once (one thread each)")
    ap.add_argument("--redo", action="store_true", help="drive sets whose table exists again")
    args = ap.parse_args()
    if not args.bundle.is_file():
        raise SystemExit(f"--bundle: no planner bundle at {args.bundle}")
    if args.jobs < 1:
        raise SystemExit(f"--jobs: expected at least 1, got {args.jobs}")
    if args.against is not None:
        missing = [s for s in args.sets if not (args.against / s / "closed_loop.csv").is_file()]
        if missing:
            raise SystemExit(f"--against: {args.against} has no run of the sets {missing}")
    done = [s for s in args.sets if (args.out / s / "closed_loop.csv").is_file() and not args.redo]
    with ThreadPoolExecutor(args.jobs) as pool:
        dirs = list(pool.map(lambda s: drive(s, args.bundle, args.out, args.check, args.redo),
                             args.sets))  # fmt: skip
    runs = {s: load_run(d, PLANNER, s) for s, d in zip(args.sets, dirs)}
    against = None
    if args.against is not None:
        against = {s: load_run(args.against / s, PLANNER, f"--against {s}") for s in args.sets}
    print(f"# closed-loop dev sets, {args.bundle}, check={args.check or '{}'}: {args.out}")
    if done:
        print(f"# read, not driven again (--redo drives them): {' '.join(done)}")
    print(table(runs, against))


if __name__ == "__main__":
    main()
