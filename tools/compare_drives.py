"""Compare two closed-loop runs scene by scene (Hydra entry point; configs/compare_drives.yaml).

    python tools/compare_drives.py a=outputs/drive_off b=outputs/drive_on [planner=world_model]
        [planner_b=rule_based] [top=5] [out=comparison.md]
    python tools/compare_drives.py 'a=[run_seed0,run_seed1]' 'b=[other_seed0,other_seed1]'

Pairs the two runs' ``closed_loop.csv`` rows of one planner by scene
(:mod:`renderworld.sim.closed_loop.compare`) and prints the mean scores of both, how many scenes
went up and down, per behaviour, and the scenes that moved most. A side given as a list of runs
(e.g. the bundles of several trainings) is compared by each scene's mean over its runs, and
each run's own mean is printed beside it.
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from renderworld.sim.closed_loop.compare import (  # noqa: E402
    average_runs,
    compare_runs,
    comparison_markdown,
    load_run,
    run_spread,
    spread_markdown,
)


def _paths(value) -> list[str]:
    """A run directory, or a list of them (Hydra ``a=[x,y]``)."""
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value]


def compare(cfg: DictConfig) -> dict:
    """Run the config; returns the comparison (``compare_runs``) and its markdown."""
    pb = str(cfg.planner_b) if cfg.get("planner_b") else str(cfg.planner)
    pa, pbs = _paths(cfg.a), _paths(cfg.b)
    runs_a = [load_run(p, str(cfg.planner), "a") for p in pa]
    runs_b = [load_run(p, pb, "b") for p in pbs]
    cmp = compare_runs(average_runs(runs_a, "a"), average_runs(runs_b, "b"), top=int(cfg.top))
    md = comparison_markdown(cmp, f"a ({cfg.planner})", f"b ({pb})")
    common = [s for s in runs_a[0].index if s in runs_b[0].index]
    spread = spread_markdown({"a": run_spread(runs_a, common), "b": run_spread(runs_b, common)})
    md = md + ("\n\n" + spread if spread else "")
    print(f"a = {', '.join(pa)} ({cfg.planner}), b = {', '.join(pbs)} ({pb}), "
          f"{cmp['scenes']} scenes paired\n")  # fmt: skip
    print(md)
    if cfg.get("out"):
        Path(str(cfg.out)).write_text(md + "\n")
    return {"comparison": cmp, "markdown": md}


@hydra.main(config_path="../configs", config_name="compare_drives", version_base=None)
def main(cfg: DictConfig) -> None:
    """Compare."""
    compare(cfg)


if __name__ == "__main__":
    main()
