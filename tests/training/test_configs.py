"""Compose every config in the tree; structured-config validation; grids agree with constants."""

from __future__ import annotations

import importlib

import pytest
from omegaconf import OmegaConf

from renderworld.constants import GRIDS
from renderworld.training.config import (
    OptimizerConfig,
    SchedulerConfig,
    TrainerConfig,
    grid_spec_from_config,
    validate_group,
)
from renderworld.training.registry import get_stage

from .conftest import CONFIGS, TEST_CONFIGS, compose_cfg

# sim/ and bench/ are groups of their own tools (make_fixtures, bench), not of train.yaml.
GROUPS = sorted(p.name for p in CONFIGS.iterdir() if p.is_dir() and p.name not in ("sim", "bench"))


def _options(group: str) -> list[str]:
    names = {p.stem for p in (CONFIGS / group).glob("*.yaml")}
    names |= {p.stem for p in (TEST_CONFIGS / group).glob("*.yaml")}
    return sorted(names)


def _groups_of(config_name: str) -> list[str]:
    """The groups in a primary config's defaults list."""
    defaults = OmegaConf.load(CONFIGS / f"{config_name}.yaml").defaults
    return [next(iter(d)) for d in defaults if not isinstance(d, str)]


CASES = [(c, g, o) for c in ("train", "eval") for g in _groups_of(c) for o in _options(g)]


def test_every_group_is_reachable_from_train_yaml():
    assert sorted(_groups_of("train")) == GROUPS


@pytest.mark.parametrize(
    ("config_name", "group", "option"), CASES, ids=[f"{c}-{g}={o}" for c, g, o in CASES]
)
def test_every_option_composes_and_resolves(config_name, group, option, tmp_path):
    overrides = [f"run_dir={tmp_path}", f"{group}={option}"]
    if group != "stage":
        overrides.append("stage=regression")
    if config_name == "eval":
        overrides.append("ckpt=some.pt")
    cfg = compose_cfg(overrides, config_name=config_name)
    # A stage's required upstream inputs (``???``, e.g. stage.tokenizer_ckpt) and the weights
    # a fine-tuning starts from (init_from) are the user's to pass on the command line; nothing
    # else may be left missing.
    for key in OmegaConf.missing_keys(cfg):
        assert key.startswith("stage.") or key == "init_from", f"{key} is ??? but is not an input"
        OmegaConf.update(cfg, key, "upstream.pt")
    resolved = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    assert resolved["stage"]["name"]
    # Library-facing groups must satisfy their schemas, whatever the option or experiment.
    validate_group(cfg.trainer, TrainerConfig, "trainer")
    if config_name == "train":
        validate_group(cfg.optimizer, OptimizerConfig, "optimizer")
        validate_group(cfg.scheduler, SchedulerConfig, "scheduler")
    grid_spec_from_config(cfg.grid)


def test_hydra_node_of_every_experiment_composes(tmp_path):
    for option in _options("experiment") + [f"hp:{o}" for o in _options("hparams_search")]:
        override = (
            f"hparams_search={option[3:]}" if option.startswith("hp:") else f"experiment={option}"
        )
        cfg = compose_cfg(["stage=regression", override], hydra_cfg=True)
        assert cfg.hydra.run.dir.startswith("outputs/")
        assert cfg.hydra.job.chdir is False


def test_experiment_lists_only_deltas():
    cfg = compose_cfg(["experiment=budget_10min", "stage=regression"])
    base = compose_cfg(["stage=regression"])
    assert cfg.trainer.max_minutes == 10 and base.trainer.max_minutes is None
    assert cfg.grid.name == "coarse" and cfg.trainer.precision == "bf16"
    assert cfg.optimizer == base.optimizer  # untouched groups stay the defaults


def test_stage_is_required():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="stage"):
        compose_cfg([])


@pytest.mark.parametrize(
    "stage_file",
    sorted(CONFIGS.glob("stage/*.yaml")) + sorted(TEST_CONFIGS.glob("stage/*.yaml")),
    ids=lambda p: p.stem,
)
def test_every_stage_config_points_at_a_registered_stage(stage_file):
    node = OmegaConf.load(stage_file)
    assert node.name == stage_file.stem, "a stage yaml is named after its stage"
    module = node.get("_target_module_")
    assert module, f"{stage_file}: set _target_module_ to the module registering the stage"
    importlib.import_module(module)
    assert get_stage(node.name, module).name == node.name


@pytest.mark.parametrize("name", sorted(GRIDS))
def test_grid_configs_equal_constants(name):
    node = OmegaConf.load(CONFIGS / "grid" / f"{name}.yaml")
    cfg = compose_cfg(["stage=regression", f"grid={name}"])
    assert grid_spec_from_config(cfg.grid) == GRIDS[name], node


def test_validate_group_rejects_bad_values():
    with pytest.raises(ValueError, match="trainer.batch_sz"):
        validate_group({"batch_sz": 2}, TrainerConfig, "trainer")
    with pytest.raises(ValueError, match="trainer.batch_size.*could not be converted"):
        validate_group({"batch_size": "two"}, TrainerConfig, "trainer")
    with pytest.raises(ValueError, match="trainer.batch_size: expected a positive value, got 0"):
        validate_group({"batch_size": 0}, TrainerConfig, "trainer")
    with pytest.raises(ValueError, match=r"trainer.precision: expected one of .* got 'fp8'"):
        validate_group({"precision": "fp8"}, TrainerConfig, "trainer")
    with pytest.raises(ValueError, match="set max_steps or max_epochs"):
        validate_group({"max_steps": None}, TrainerConfig, "trainer")
    with pytest.raises(ValueError, match="optimizer.name: expected one of"):
        validate_group({"name": "adam"}, OptimizerConfig, "optimizer")
    with pytest.raises(ValueError, match="optimizer.betas"):
        validate_group({"betas": [0.9, 1.5]}, OptimizerConfig, "optimizer")
    with pytest.raises(ValueError, match="scheduler.min_lr_ratio"):
        validate_group({"min_lr_ratio": 2.0}, SchedulerConfig, "scheduler")
    with pytest.raises(ValueError, match="trainer: the config group is missing"):
        validate_group(None, TrainerConfig, "trainer")


def test_grid_spec_from_config_rejects_bad_grids():
    good = {"name": "g", "range_min": [0, 0, 0], "range_max": [1, 1, 1], "shape": [2, 2, 2]}
    assert grid_spec_from_config(good).voxel_size == (0.5, 0.5, 0.5)
    with pytest.raises(ValueError, match="expected keys name, range_min"):
        grid_spec_from_config({"name": "g"})
    with pytest.raises(ValueError, match="need range_max > range_min"):
        grid_spec_from_config({**good, "range_max": [1, 0, 1]})
    with pytest.raises(ValueError, match="need 3 values each"):
        grid_spec_from_config({**good, "shape": [2, 2]})
