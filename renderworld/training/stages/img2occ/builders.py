"""Builders of the ``img2occ`` stage: its model config, datasets and trained model from a run.

Shared by the stage (``stage``), its end-of-training readout selection (``threshold``)
and the pseudo-label export (``export``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from omegaconf import OmegaConf
from torch.utils.data import Dataset

from renderworld.img2occ import Img2Occ, Img2OccConfig
from renderworld.training.checkpoint import check_state_dict_keys, load_checkpoint
from renderworld.training.stages.common import grid_of, infos_dir, warn_architecture_differs

__all__ = ["checkpoint_architecture", "img2occ_config", "img2occ_datasets", "load_img2occ"]

# Stage-level keys that fill these Img2OccConfig fields (never set them under stage.model).
_STAGE_FIELDS = ("grid", "input_size", "render_size", "adjacent_frames")
# Options of how a trained model is run, not of its weights: an evaluation keeps the run's
# (e.g. ``mirror_readout=false`` scores the same weights without the mirrored readout).
_RUN_FIELDS = ("mirror_readout", "lift_sparse", "render_backend", "prune_opacity")


def _size(cfg: Any, key: str) -> tuple[int, int]:
    value = cfg.stage.get(key)
    try:
        h, w = (int(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"stage.{key}: expected [H, W] pixels, got {value!r}") from None
    return h, w


def _adjacent(cfg: Any) -> int:
    k = cfg.stage.get("adjacent_frames", 0)
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise ValueError(f"stage.adjacent_frames: expected an integer k >= 0, got {k!r}")
    return k


def img2occ_config(cfg: Any) -> Img2OccConfig:
    """The :class:`Img2OccConfig` of a run config.

    ``stage.model`` holds Img2OccConfig fields; the grid comes from the ``grid`` group and
    ``input_size``, ``render_size``, ``adjacent_frames`` (k > 0 turns the model's adjacent-view
    losses on) from the stage's own keys, shared with the datasets.

    Raises:
        ValueError: an unknown ``stage.model`` key, a stage-level field set under
            ``stage.model``, or an invalid value (the message names the key).
    """
    model = OmegaConf.to_container(cfg.stage.model, resolve=True) if cfg.stage.get("model") else {}
    names = {f.name for f in dataclasses.fields(Img2OccConfig)}
    for key in model:
        if key in _STAGE_FIELDS:
            raise ValueError(
                f"stage.model.{key}: set by the run config ("
                + ("the grid group" if key == "grid" else f"stage.{key}")
                + "), not under stage.model"
            )
        if key not in names:
            raise ValueError(
                f"stage.model.{key}: not an Img2OccConfig field; expected one of "
                f"{sorted(names - set(_STAGE_FIELDS))}"
            )
    try:
        return Img2OccConfig(
            grid=grid_of(cfg),
            input_size=_size(cfg, "input_size"),
            render_size=_size(cfg, "render_size"),
            adjacent_frames=_adjacent(cfg) > 0,
            **model,
        )
    except (TypeError, ValueError) as err:
        raise ValueError(f"stage (Img2OccConfig): {err}") from None


def checkpoint_architecture(mine: Img2OccConfig, ckpt) -> Img2OccConfig:
    """The model config to evaluate checkpoint ``ckpt`` with: its stored ``stage.model``, the
    run's input and render sizes (the data the run reads) and the run's options of how the
    model runs (``_RUN_FIELDS``: the readout, the lifting's and the rasterizer's paths).

    A warning names the ``stage.model`` values that differ from the run's ``mine``.

    Raises:
        ValueError: naming ``ckpt`` when it was trained on another grid.
        CheckpointError: the file is not an img2occ checkpoint.
    """
    stored = load_checkpoint(ckpt, expected_stage="img2occ")["config"]
    theirs = img2occ_config(OmegaConf.create(stored))
    if theirs.grid != mine.grid:
        raise ValueError(
            f"ckpt: {str(ckpt)!r} was trained on the {theirs.grid.name!r} grid "
            f"{theirs.grid.shape}, the run's is {mine.grid.name!r} {mine.grid.shape} (grid=...)"
        )
    kept = ("input_size", "render_size", "adjacent_frames", *_RUN_FIELDS)
    theirs = dataclasses.replace(theirs, **{k: getattr(mine, k) for k in kept})
    warn_architecture_differs(ckpt, theirs, mine)
    return theirs


def img2occ_datasets(cfg: Any, split: str, adjacent_frames: int = 0) -> Dataset:
    """An ``Img2OccDataset`` of one converter split at the run's sizes and grid.

    Args:
        cfg: run config (``dataset``, ``grid``, ``stage``).
        split: split name (``infos_<split>.parquet`` in :func:`infos_dir`).
        adjacent_frames: k neighbouring keyframes on each side as label-only views.
    """
    from renderworld.data import Img2OccDataset, load_infos

    return Img2OccDataset(
        load_infos(infos_dir(cfg), split),
        str(cfg.dataset.data_root),
        input_size=_size(cfg, "input_size"),
        render_size=_size(cfg, "render_size"),
        grid=grid_of(cfg),
        adjacent_frames=adjacent_frames,
    )


def load_img2occ(path, device: str | torch.device = "cpu") -> tuple[Img2Occ, dict[str, Any]]:
    """Rebuild a trained Img2Occ from an ``img2occ`` checkpoint (its stored config), eval mode.

    Args:
        path: ``last.pt`` / ``best.pt`` written by ``tools/train.py stage=img2occ``.
        device: where to put the model.

    Returns:
        ``(model, checkpoint dict)``; the readout threshold is the checkpoint's.

    Raises:
        CheckpointError: the file is not an img2occ checkpoint or its weights do not fit.
    """
    ckpt = load_checkpoint(path, expected_stage="img2occ")
    model = Img2Occ(img2occ_config(OmegaConf.create(ckpt["config"])))
    check_state_dict_keys(model, ckpt["model"], f"checkpoint {str(path)!r}")
    model.load_state_dict(ckpt["model"], strict=True)
    model.to(device).eval()
    return model, ckpt
