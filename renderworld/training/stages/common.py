"""Helpers shared by the stages: dataset locations, grids and occupancy confusion statistics."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any

import torch

from renderworld.constants import GridSpec
from renderworld.metrics.occupancy import (
    confusion_counts,
    geometry_iou,
    iou_per_class,
    mean_iou,
)
from renderworld.training.config import grid_spec_from_config

__all__ = [
    "infos_dir",
    "grid_of",
    "confusion_stats",
    "occupancy_metrics",
    "evaluated_checkpoint",
    "warn_architecture_differs",
]


def infos_dir(cfg: Any) -> Path:
    """Folder of ``infos_<split>.parquet``: ``stage.infos_dir`` or the converter's default.

    The default is ``<dataset.data_root>/renderworld_infos/<dataset.version>`` (what
    ``tools/create_data.py`` writes when given no ``out``).

    Raises:
        ValueError: when the folder does not exist (names it and the command that makes it).
    """
    explicit = cfg.stage.get("infos_dir") if "stage" in cfg else None
    root = Path(str(cfg.dataset.data_root))
    path = Path(explicit) if explicit else root / "renderworld_infos" / str(cfg.dataset.version)
    if not path.is_dir():
        raise ValueError(
            f"stage.infos_dir: {path} does not exist; run tools/create_data.py "
            f"data_root={root} version={cfg.dataset.version} first"
        )
    return path


def grid_of(cfg: Any) -> GridSpec:
    """The run's grid (config group ``grid``)."""
    return grid_spec_from_config(cfg.grid)


def confusion_stats(
    pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """18x18 confusion (rows = ground truth) as float64, summable across ranks.

    Args:
        pred: [...] integer Occ3D ids.
        gt: [...] integer Occ3D ids, same shape.
        mask: optional [...] bool; only True voxels count.

    Returns:
        [18, 18] float64 on the inputs' device, counted by
        :func:`renderworld.metrics.occupancy.confusion_counts` (no host sync beyond bincount's).

    Raises:
        ValueError: as ``confusion_counts`` (labels outside [0, 17] name the argument).
    """
    return confusion_counts(pred, gt, mask).double()


def occupancy_metrics(confusion: torch.Tensor, prefix: str) -> dict[str, float]:
    """mIoU over classes 0..16 (free excluded), geometry IoU and per-class IoU from a confusion."""
    conf = confusion.cpu().numpy()
    per_class = iou_per_class(conf)
    out = {f"{prefix}miou": float(mean_iou(conf)), f"{prefix}iou": float(geometry_iou(conf))}
    from renderworld.constants import OCC3D_CLASSES

    for c, name in enumerate(OCC3D_CLASSES[:-1]):
        out[f"{prefix}iou_{name}"] = float(per_class[c])
    return out


def evaluated_checkpoint(cfg: Any) -> str | None:
    """The checkpoint an evaluation run (``task: eval``) scores, when ``ckpt`` names a file;
    else None (training, or no such file yet: the caller builds the run's own model)."""
    ckpt = cfg.get("ckpt") if cfg.get("task") == "eval" else None
    return str(ckpt) if ckpt and Path(str(ckpt)).is_file() else None


def warn_architecture_differs(ckpt: Any, theirs: Any, mine: Any) -> None:
    """Warn, naming checkpoint ``ckpt`` and each field, where the model config it was trained
    with (``theirs``, a dataclass) differs from the run's ``stage.model`` (``mine``), before an
    evaluation builds the checkpoint's architecture."""
    diff = {
        f.name: getattr(theirs, f.name)
        for f in dataclasses.fields(theirs)
        if getattr(theirs, f.name) != getattr(mine, f.name)
    }
    if diff:
        warnings.warn(
            f"ckpt: {str(ckpt)!r} was trained with stage.model "
            + ", ".join(f"{k}={v!r}" for k, v in diff.items())
            + "; evaluating that architecture",
            stacklevel=3,
        )
