"""Train a stage:  python tools/train.py stage=<name> [experiment=...] [key=value ...]

Multi-process: torchrun --nproc_per_node=N tools/train.py stage=<name> ...
Resume:        python tools/train.py stage=<name> run_dir=<run> resume=true
See configs/README.md.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a clone without install

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from renderworld.training import hydra_argv, objective, train  # noqa: E402


@hydra.main(version_base="1.3", config_path="../configs", config_name="train")
def main(cfg: DictConfig) -> float | None:
    return objective(cfg, train(cfg))


if __name__ == "__main__":
    sys.argv = hydra_argv(sys.argv)
    main()
