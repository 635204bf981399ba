"""Bundle a world-model run and its tokenizer into one planner file.

    python tools/export_planner.py world_model_ckpt=PATH tokenizer_ckpt=PATH out=FILE

Either forecaster (``stage.forecaster=tokens`` or ``pose_warp``, the main job's). Load the
file with ``renderworld.planning.load_planner(FILE)``. Thin Hydra wrapper around
:func:`renderworld.training.stages.world_model.bundle.export_planner_bundle`
(configs/export_planner.yaml); the main job runs it as its ``planner`` step.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a clone without install

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from renderworld.training.stages.world_model.bundle import export_planner_bundle  # noqa: E402


@hydra.main(config_path="../configs", config_name="export_planner", version_base=None)
def main(cfg: DictConfig) -> str:
    """Write the bundle and print its path; returns it."""
    out = Path(str(cfg.out))
    out.parent.mkdir(parents=True, exist_ok=True)
    path = export_planner_bundle(cfg.world_model_ckpt, cfg.tokenizer_ckpt, out)
    print(f"planner bundle: {path}", flush=True)
    return str(path)


if __name__ == "__main__":
    main()
