"""Evaluate a checkpoint:  python tools/eval.py stage=<name> ckpt=PATH [key=value ...]

Writes eval_metrics.json into outputs/eval/<stage>/<time>/ (or run_dir=PATH). See
configs/README.md.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a clone without install

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from renderworld.training import evaluate, hydra_argv  # noqa: E402


@hydra.main(version_base="1.3", config_path="../configs", config_name="eval")
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    sys.argv = hydra_argv(sys.argv)
    main()
