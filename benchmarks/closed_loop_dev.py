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

The loop is chaotic: started 1 mm ahead of the log (``tools/drive.py nudge_m=0.001``), the
checked plan scores differently in most scenes (``docs/closed_loop.md`` § "The loop's own
noise"). ``--nudges 0 0.001 -0.001`` drives every set from each start (nudge 0 into
``<out>/<set>/``, the others into ``<out>/nudge<+x>/<set>/``) and scores each scene by its mean
over them; the at-fault and comfort columns are then mean counts per start, and ``--against``
must hold the same starts.

Usage::

    python benchmarks/closed_loop_dev.py --bundle outputs/demo/planner/planner.pt \\
        --out outputs/dev_loop/base
    python benchmarks/closed_loop_dev.py --bundle outputs/demo/planner/planner.pt \\
        --check '{change_cost: 0.1}' --out outputs/dev_loop/cost01 --against outputs/dev_loop/base
    python benchmarks/closed_loop_dev.py --bundle outputs/demo/planner/planner.pt \\
        --nudges 0 0.001 -0.001 --out outputs/dev_loop/base3
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

from renderworld.sim.closed_loop.compare import (  # noqa: E402
    average_runs,
    compare_runs,
    event_count,
    load_run,
)

#: The development sets: name -> ``tools/drive.py`` arguments (docs/protocol.md).
SETS = {
    "turns": ["preset=scenarios", "behaviours=[turn_left,turn_right]"],
    "routes": ["preset=scenarios", "behaviours=[cruise,stop_and_go,lane_change_left,parked]"],
    "pdev": ["preset=scenarios", "behaviours=interactions", "max_scenes=50"],
    "pdevi": ["preset=interactions", "seed=1002", "num_scenes=64"],
}
PLANNER = "world_model"


def start_dir(out: Path, nudge_m: float) -> Path:
    """Where the sets driven from a start ``nudge_m`` metres ahead of the log lie (module
    docstring): ``out`` itself for the log's own start."""
    return out if nudge_m == 0 else out / f"nudge{nudge_m:+g}"


def drive(
    name: str, bundle: Path, out: Path, check: str | None, redo: bool, nudge_m: float = 0.0
) -> Path:
    """Drive one set (skipped where its table is already there); returns its run directory.

    Raises:
        RuntimeError: naming the set and its log when ``tools/drive.py`` fails.
    """
    out = start_dir(out, nudge_m)
    run = out / name
    if (run / "closed_loop.csv").is_file() and not redo:
        return run
    cmd = [sys.executable, str(ROOT / "tools" / "drive.py"), *SETS[name], "planners=[]",
           f"planner={bundle}", "threads=1", f"out={run}"]  # fmt: skip
    if check:
        cmd.append(f"check={check}")
    if nudge_m:
        cmd.append(f"nudge_m={nudge_m!r}")
    out.mkdir(parents=True, exist_ok=True)
    log = out / f"{name}.log"
    with open(log, "w") as f:
        rc = subprocess.run(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise RuntimeError(f"set {name}: tools/drive.py failed with exit code {rc}; see {log}")
    return run


def summary(rows: pd.DataFrame) -> dict:
    """Scores of a planner's rows (:func:`~renderworld.sim.closed_loop.compare.load_run`, or
    several starts' :func:`~renderworld.sim.closed_loop.compare.average_runs`): mean PDMS, EP
    and TTC, and the scenes with an at-fault contact and with comfort lost (mean counts per
    start)."""
    return {
        "scenes": len(rows),
        "PDMS": float(rows["PDMS"].mean()),
        "at_fault": event_count(rows["at_fault_collision"]),
        "comfort_fails": float((1.0 - rows["C"].astype(float)).sum()),
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
        line = (f"| {name} | {s['scenes']} | {s['PDMS']:.3f} | {_count(s['at_fault'])} | "
                f"{_count(s['comfort_fails'])} | {s['EP']:.3f} | {s['TTC']:.3f} |")  # fmt: skip
        if against:
            base = {**against, **base_every}[name]
            o = compare_runs(base, rows)["overall"]
            line += f" {o['PDMS_b'] - o['PDMS_a']:+.3f} ± {o['PDMS_se']:.3f} |"
        lines.append(line)
    return "\n".join(lines)


def _count(x: float) -> str:
    """A count, or a mean count over several starts to two decimals."""
    return f"{x:.0f}" if round(float(x), 6).is_integer() else f"{x:.2f}"


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
    ap.add_argument(
        "--nudges",
        type=float,
        nargs="+",
        default=[0.0],
        help="starts, metres ahead of the log (e.g. 0 0.001 -0.001): every set is "
        "driven from each, each scene scored by its mean over them",
    )
    args = ap.parse_args()
    if not args.bundle.is_file():
        raise SystemExit(f"--bundle: no planner bundle at {args.bundle}")
    if args.jobs < 1:
        raise SystemExit(f"--jobs: expected at least 1, got {args.jobs}")
    nudges = list(dict.fromkeys(args.nudges))
    if not all(abs(n) < 1.0 for n in nudges):
        raise SystemExit(f"--nudges: expected starts within 1 m of the log's, got {nudges}")
    jobs = [(s, n) for n in nudges for s in args.sets]

    def have(root: Path) -> list[str]:  # the jobs whose table ``root`` holds, as folder/set
        return [f"{start_dir(root, n).name}/{s}" for s, n in jobs
                if (start_dir(root, n) / s / "closed_loop.csv").is_file()]  # fmt: skip

    if args.against is not None:
        held = have(args.against)
        missing = [f"{start_dir(args.against, n).name}/{s}" for s, n in jobs]
        missing = [m for m in missing if m not in held]
        if missing:
            raise SystemExit(f"--against: {args.against} has no run of {missing}")
    done = [] if args.redo else have(args.out)
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda j: drive(j[0], args.bundle, args.out, args.check, args.redo, j[1]),
                      jobs))  # fmt: skip

    def side(root: Path, s: str, label: str):
        return average_runs([load_run(start_dir(root, n) / s, PLANNER, f"{label}{s}")
                             for n in nudges], f"{label}{s}")  # fmt: skip

    runs = {s: side(args.out, s, "") for s in args.sets}
    against = None
    if args.against is not None:
        against = {s: side(args.against, s, "--against ") for s in args.sets}
    starts = f", starts {nudges} m ahead of the log" if nudges != [0.0] else ""
    print(f"# closed-loop dev sets, {args.bundle}, check={args.check or '{}'}{starts}: {args.out}")
    if done:
        print(f"# read, not driven again (--redo drives them): {' '.join(done)}")
    print(table(runs, against))


if __name__ == "__main__":
    main()
