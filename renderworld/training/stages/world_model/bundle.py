"""Planner bundles from ``world_model`` runs (:func:`export_planner_bundle`)."""

from __future__ import annotations

import os
from pathlib import Path

from omegaconf import OmegaConf

from renderworld.planning import register_tokenizer, save_planner_bundle
from renderworld.tokenizer import SceneTokenizer, build_tokenizer
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.stages.common import grid_of
from renderworld.training.stages.tokenizer import load_tokenizer
from renderworld.training.stages.world_model.settings import (
    build_world_model,
    check_same_tokenizer,
    forecaster_of,
    world_model_config,
)

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

    Either forecaster: ``stage.forecaster=tokens`` (:class:`renderworld.world.WorldModel`) or
    ``pose_warp`` (:class:`renderworld.world.pose.PoseWarpWorldModel`, the main job's; its pose
    head's anchors and the run's grid are stored with it).

    Args:
        world_model_ckpt: ``last.pt`` / ``best.pt`` of a ``world_model`` run.
        tokenizer_ckpt: the ``tokenizer`` checkpoint that run was trained on.
        out_path: bundle file to write (its folder must exist); load it with
            ``renderworld.planning.load_planner(out_path)`` (the package's tokenizer kind
            ``"scene_tokenizer"`` is registered there too).

    Returns:
        ``out_path``.

    Raises:
        CheckpointError: a checkpoint that is missing, of another stage, or does not fit.
        ValueError: a tokenizer checkpoint other than the one the run was trained on.
    """
    from renderworld.training.checkpoint import check_state_dict_keys

    ckpt = load_checkpoint(world_model_ckpt, expected_stage="world_model")
    cfg = OmegaConf.create(ckpt["config"])
    kind = forecaster_of(cfg)
    check_same_tokenizer(cfg, tokenizer_ckpt)
    tokenizer = load_tokenizer(tokenizer_ckpt, "cpu")
    model = build_world_model(kind, world_model_config(cfg, tokenizer.cfg), cfg)
    check_state_dict_keys(model, ckpt["model"], source=f"checkpoint {str(world_model_ckpt)!r}")
    model.load_state_dict(ckpt["model"], strict=True)
    grid = grid_of(cfg) if kind == "pose_warp" else None
    return save_planner_bundle(out_path, tokenizer, model, grid=grid)
