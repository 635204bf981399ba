"""The ``world_model`` stage (``stage._target_module_: renderworld.training.stages.world_model``).

Importing this package registers :class:`WorldModelStage`. Its modules:

* ``stage``: :class:`WorldModelStage` (datasets, loss, forecasts, evaluation, report hooks);
* ``settings``: the stage's config (``stage_settings``, ``world_model_config``) and the
  evaluation settings (3D-Occ, Camera);
* ``windows``: :class:`~.windows.WorldModelWindows`, the training / validation windows;
* ``frozen_tokenizers``: the frozen tokenizers and their cached codes (a mixin);
* ``checkpoints``: world models built from configs and checkpoints (a mixin);
* ``pose_warp``: training and forecasting with ``stage.forecaster: pose_warp``;
* ``evaluation``, ``splits``, ``heading``: additive statistics of the evaluation and the
  metrics rebuilt from them;
* ``references``: the forecasts that read the future, reported as references ("(ref.)");
* ``report``, ``pictures``: the results table and figures of an evaluation;
* ``bundle``: :func:`export_planner_bundle` (a trained run as a planner bundle).
"""

from renderworld.training.stages.world_model.bundle import TOKENIZER_KIND, export_planner_bundle
from renderworld.training.stages.world_model.settings import world_model_config
from renderworld.training.stages.world_model.stage import WorldModelStage

__all__ = [
    "WorldModelStage",
    "world_model_config",
    "export_planner_bundle",
    "TOKENIZER_KIND",
]
