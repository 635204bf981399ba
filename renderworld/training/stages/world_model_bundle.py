"""Planner bundles from ``world_model`` runs (:func:`export_planner_bundle`)."""

from __future__ import annotations

import os
from pathlib import Path

from omegaconf import OmegaConf

from renderworld.planning import register_tokenizer, save_planner_bundle
from renderworld.tokenizer import SceneTokenizer, build_tokenizer
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.stages.tokenizer import load_tokenizer
from renderworld.training.stages.world_model_settings import (
    check_same_tokenizer,
    forecaster_of,
    world_model_config,
)
from renderworld.world import WorldModel

__all__ = ["export_planner_bundle", "TOKENIZER_KIND"]

#: Name of :class:`SceneTokenizer` in planner bundles.
TOKENIZER_KIND = "scene_tokenizer"
register_tokenizer(TOKENIZER_KIND, SceneTokenizer, from_config=build_tokenizer)


def export_planner_bundle(
    world_model_ckpt: str | os.PathLike,
    tokenizer_ckpt: str | os.PathLike,
    out_path: str | os.PathLike,
) -> Path:
    """Write a :mod:`renderworld.planning` bundle from a world-model and a tokenizer checkpoint.

    Args:
        world_model_ckpt: ``last.pt`` / ``best.pt`` of a ``world_model`` run.
        tokenizer_ckpt: the ``tokenizer`` checkpoint that run was trained on.
        out_path: bundle file to write (its folder must exist); load it with
            ``renderworld.planning.load_planner(out_path)`` after importing this module (which
            registers the tokenizer kind ``"scene_tokenizer"``).

    Returns:
        ``out_path``.

    Raises:
        CheckpointError: a checkpoint that is missing, of another stage, or does not fit.
        ValueError: a ``stage.forecaster=pose_warp`` checkpoint (not a planner world model).
    """
    from renderworld.training.checkpoint import check_state_dict_keys

    ckpt = load_checkpoint(world_model_ckpt, expected_stage="world_model")
    cfg = OmegaConf.create(ckpt["config"])
    kind = forecaster_of(cfg)
    if kind != "tokens":
        raise ValueError(
            f"world_model_ckpt: {str(world_model_ckpt)!r} is a stage.forecaster={kind!r} model; "
            "planner bundles hold the token world model (stage.forecaster=tokens) only"
        )
    check_same_tokenizer(cfg, tokenizer_ckpt)
    tokenizer = load_tokenizer(tokenizer_ckpt, "cpu")
    model = WorldModel(world_model_config(cfg, tokenizer.cfg))
    check_state_dict_keys(model, ckpt["model"], source=f"checkpoint {str(world_model_ckpt)!r}")
    model.load_state_dict(ckpt["model"], strict=True)
    return save_planner_bundle(out_path, tokenizer, model)
