"""Models for the viewer from the training runs' files; a missing file skips its layer.

The checkpoints hold their run's resolved config as YAML, so rebuilding a model uses the
training stages' own loaders (imported here on call; they need OmegaConf, not Rerun).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["ViewerModels", "load_viewer_models"]

PathLike = str | os.PathLike | None


class ViewerModels(dict):
    """``{"img2occ": Img2Occ | None, "tokenizer": SceneTokenizer | None, "planner": Planner |
    None}``, usable as ``write_scene_recording(..., **models, reasons=models.reasons)``.

    Attributes:
        reasons: {layer: why its model is missing} for files given but absent.
    """

    def __init__(self, **models):
        super().__init__(**models)
        self.reasons: dict[str, str] = {}


def _given(path: PathLike, key: str, layer: str, reasons: dict) -> Path | None:
    if path is None or str(path) == "":
        return None
    p = Path(path)
    if not p.is_file():
        reasons[layer] = f"{key} {str(p)!r} does not exist"
        return None
    return p


def load_viewer_models(
    img2occ_ckpt: PathLike = None,
    tokenizer_ckpt: PathLike = None,
    world_model_ckpt: PathLike = None,
    planner_bundle: PathLike = None,
    device: str = "cpu",
) -> ViewerModels:
    """Load the models whose files are given and exist, in eval mode on ``device``.

    Args:
        img2occ_ckpt: an ``img2occ`` run's ``best.pt`` / ``last.pt`` (Gaussians, read-out).
        tokenizer_ckpt: a ``tokenizer`` run's checkpoint (reconstruction; with
            ``world_model_ckpt`` also the planner's tokenizer).
        world_model_ckpt: a ``world_model`` run's checkpoint (forecasts and plans).
        planner_bundle: a planner bundle (``renderworld.planning``), used instead of
            ``world_model_ckpt`` + ``tokenizer_ckpt`` for the forecast layer.
        device: where the models run.

    Returns:
        :class:`ViewerModels` (None for each model not loaded; ``reasons`` says why for
        the files that were given; :func:`write_scene_recording` prints them as its skip lines).

    Raises:
        CheckpointError (a ValueError): a file that exists but is not a checkpoint of that
            stage, or whose weights do not fit its config (the message names the file).
    """
    models = ViewerModels(img2occ=None, tokenizer=None, planner=None)
    why = models.reasons
    path = _given(img2occ_ckpt, "img2occ_ckpt", "img2occ", why)
    if path is not None:
        from renderworld.training.stages.img2occ import load_img2occ

        models["img2occ"] = load_img2occ(path, device)[0]
    path = _given(tokenizer_ckpt, "tokenizer_ckpt", "tokenizer", why)
    if path is not None:
        from renderworld.training.stages.tokenizer import load_tokenizer

        models["tokenizer"] = load_tokenizer(path, device)
    bundle = _given(planner_bundle, "planner_bundle", "forecast", why)
    if bundle is not None:
        from renderworld.planning import load_planner

        # (registers the scene tokenizer with the planner bundles)
        from renderworld.training.stages.world_model import bundle as _registers  # noqa: F401

        models["planner"] = load_planner(bundle, device)
        return models
    path = _given(world_model_ckpt, "world_model_ckpt", "forecast", why)
    if path is not None and models["tokenizer"] is None:
        why["forecast"] = why.get("tokenizer", "world_model_ckpt needs its tokenizer_ckpt")
    elif path is not None:
        models["planner"] = _planner(path, models["tokenizer"], Path(tokenizer_ckpt), device)
    return models


def _planner(world_model_ckpt: Path, tokenizer, tokenizer_ckpt: Path, device: str):
    """A ``Planner`` of a world-model checkpoint on an already loaded tokenizer (a warning when
    ``tokenizer_ckpt`` is not the file the world model was trained on)."""
    from omegaconf import OmegaConf

    from renderworld.planning import Planner
    from renderworld.training.checkpoint import check_state_dict_keys, load_checkpoint
    from renderworld.training.stages.common import grid_of
    from renderworld.training.stages.world_model.settings import (
        build_world_model,
        check_same_tokenizer,
        forecaster_of,
        world_model_config,
    )

    ckpt = load_checkpoint(world_model_ckpt, expected_stage="world_model")
    cfg = OmegaConf.create(ckpt["config"])
    check_same_tokenizer(cfg, tokenizer_ckpt)
    kind = forecaster_of(cfg)
    model = build_world_model(kind, world_model_config(cfg, tokenizer.cfg), cfg)
    check_state_dict_keys(model, ckpt["model"], source=f"checkpoint {str(world_model_ckpt)!r}")
    model.load_state_dict(ckpt["model"], strict=True)
    # A pose-aware model warps on its run's grid (metres per voxel), as its evaluation does.
    grid = grid_of(cfg) if kind == "pose_warp" else None
    return Planner(tokenizer, model, device=device, grid=grid)
