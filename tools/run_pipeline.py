"""The whole RenderWorld pipeline on the simulated mini fixture (what ``make demo`` runs).

    python tools/run_pipeline.py [out=outputs/demo] [force=[tokenizer]] [train_overrides=[...]]
    python tools/run_pipeline.py preset=null data_root=<nuScenes root> version=v1.0-trainval \
        experiments=paper out=outputs/paper        # real data, paper scale, one GPU

Steps (each skipped when its inputs did not change; see renderworld.pipeline.runner):
fixtures -> infos -> img2occ (train, eval, pseudo labels), beside it the scenario data, the
tokenizer (train, eval) and the world model -> the Camera setting (tokenizer and world model
fine-tuned on the pseudo labels) -> evaluation, closed loop -> report.
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from renderworld.pipeline.main_job import run_main_job  # noqa: E402


@hydra.main(config_path="../configs", config_name="pipeline", version_base=None)
def main(cfg: DictConfig) -> None:
    """Run the main job."""
    run_main_job(cfg, REPO)


if __name__ == "__main__":
    main()
