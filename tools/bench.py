"""Accuracy vs time: sweep the knobs of each stage on the same budget and tabulate the cost.

    python tools/bench.py [bench=quick|standard|full] [bench.ranking=true] [out=DIR]
        [overwrite=true] [data_root=DIR]

Prints the preset's time estimate, then writes <out>/results.csv, results.md and
pareto_<stage>.png (configs/bench.yaml explains each key; renderworld.bench.sweep how a point
is run and measured).
"""

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from renderworld.bench.main import run_bench  # noqa: E402


@hydra.main(version_base="1.3", config_path="../configs", config_name="bench")
def main(cfg: DictConfig) -> None:
    run_bench(cfg, REPO)


if __name__ == "__main__":
    main()
