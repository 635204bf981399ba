"""Compare two closed-loop runs scene by scene (Hydra entry point; configs/compare_drives.yaml).

    python tools/compare_drives.py a=outputs/drive_off b=outputs/drive_on [planner=world_model]
        [planner_b=rule_based] [top=5] [out=comparison.md]

Pairs the two runs' ``closed_loop.csv`` rows of one planner by scene
(:mod:`renderworld.sim.closed_loop.compare`) and prints the mean scores of both, how many scenes
went up and down, per behaviour, and the scenes that moved most.
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
    compare_runs,
    comparison_markdown,
    load_run,
)


def compare(cfg: DictConfig) -> dict:
    """Run the config; returns the comparison (``compare_runs``) and its markdown."""
    pb = str(cfg.planner_b) if cfg.get("planner_b") else str(cfg.planner)
    a = load_run(str(cfg.a), str(cfg.planner), "a")
    b = load_run(str(cfg.b), pb, "b")
    cmp = compare_runs(a, b, top=int(cfg.top))
    md = comparison_markdown(cmp, f"a ({cfg.planner})", f"b ({pb})")
    print(f"a = {cfg.a} ({cfg.planner}), b = {cfg.b} ({pb}), {cmp['scenes']} scenes paired\n")
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
