"""Training and evaluation: Hydra entry points' library side, checkpoints, resume, DDP, logs.

The only RenderWorld package that touches Hydra/OmegaConf objects (docs/conventions.md#layout).
Names are imported lazily, so ``from renderworld.training.checkpoint import load_model_weights``
(used by the planner API) pulls in neither OmegaConf nor the loop.

Public API:
    train(cfg) -> metrics, evaluate(cfg) -> metrics            (api)
    Stage, register_stage, get_stage, sum_count                (registry)
    save_checkpoint, load_checkpoint, load_model_weights,
    CheckpointError, CHECKPOINT_SCHEMA_VERSION                 (checkpoint)
    OptimizerConfig, SchedulerConfig, TrainerConfig,
    grid_spec_from_config                                      (config)
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "train",
    "evaluate",
    "objective",
    "hydra_argv",
    "Stage",
    "register_stage",
    "get_stage",
    "registered_stages",
    "sum_count",
    "save_checkpoint",
    "load_checkpoint",
    "load_model_weights",
    "CheckpointError",
    "CHECKPOINT_SCHEMA_VERSION",
    "OptimizerConfig",
    "SchedulerConfig",
    "TrainerConfig",
    "grid_spec_from_config",
    "seed_everything",
]

_WHERE = {
    "train": "api",
    "evaluate": "api",
    "objective": "api",
    "hydra_argv": "api",
    "Stage": "registry",
    "register_stage": "registry",
    "get_stage": "registry",
    "registered_stages": "registry",
    "sum_count": "registry",
    "save_checkpoint": "checkpoint",
    "load_checkpoint": "checkpoint",
    "load_model_weights": "checkpoint",
    "CheckpointError": "checkpoint",
    "CHECKPOINT_SCHEMA_VERSION": "checkpoint",
    "OptimizerConfig": "config",
    "SchedulerConfig": "config",
    "TrainerConfig": "config",
    "grid_spec_from_config": "config",
    "seed_everything": "seed",
}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        module = importlib.import_module(f"renderworld.training.{_WHERE[name]}")
        value = getattr(module, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'renderworld.training' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
