"""Reconstruction metrics of a tokenizer (OccWorld protocol, docs/protocol.md).

An 18x18 confusion matrix (rows: ground truth, columns: prediction) is accumulated over all
frames; per-class IoU = TP / (TP + FP + FN); mIoU is the mean over the non-air classes 0..16
of the classes with a non-empty union (free stays in the confusion but not in the mean); the
geometry IoU scores occupied (any non-air class) vs free. By default the full volume is scored;
pass ``mask`` (e.g. Occ3D's camera mask) to score only those voxels and label it as such.

This is a small torch-facing front for the tokenizer's tests and fitting; the counting itself
and the package-wide metrics live in ``renderworld.metrics``.
"""

from __future__ import annotations

import torch

from renderworld.constants import NUM_OCC3D_CLASSES
from renderworld.metrics.occupancy import (
    confusion_counts,
    geometry_iou,
    iou_per_class,
    mean_iou,
)

__all__ = ["confusion_matrix", "metrics_from_confusion", "reconstruction_metrics", "ConfusionMeter"]


def confusion_matrix(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """18x18 confusion of one batch (the package's counting rule,
    :func:`renderworld.metrics.occupancy.confusion_counts`).

    Args:
        pred: [...] integer predicted Occ3D ids.
        target: [...] integer true Occ3D ids, same shape.
        mask: Optional [...] bool, voxels to score.

    Returns:
        [18, 18] int64 on the CPU, ``conf[t, p]`` = voxels of true class t predicted as p.

    Raises:
        ValueError: shape mismatch, non-integer ids, ids outside [0, 17], a mask neither bool
            nor 0/1.
    """
    return confusion_counts(pred, target, mask, names=("pred", "target")).cpu()


def metrics_from_confusion(conf: torch.Tensor) -> dict[str, float | list[float]]:
    """Scores from an accumulated confusion matrix.

    Args:
        conf: [18, 18] integer confusion (rows truth, columns prediction).

    Returns:
        ``{"miou": mean IoU over classes 0..16 with non-empty union (nan if none),
        "iou": occupied-vs-free IoU (nan if nothing occupied in truth or prediction),
        "per_class_iou": 18 IoUs (nan where the union is empty), "num_voxels": total}``.
    """
    c = conf.double().cpu().numpy()
    iou = iou_per_class(c)
    miou, geo = mean_iou(c), geometry_iou(c)
    return {
        "miou": miou,
        "iou": geo,
        "per_class_iou": iou.tolist(),
        "num_voxels": int(conf.sum()),
    }


def reconstruction_metrics(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None
) -> dict[str, float | list[float]]:
    """mIoU (classes 0..16) and geometry IoU of one batch; see :func:`metrics_from_confusion`."""
    return metrics_from_confusion(confusion_matrix(pred, target, mask))


class ConfusionMeter:
    """Accumulates confusion over a split: ``update(pred, target)`` then ``compute()``."""

    def __init__(self) -> None:
        self.conf = torch.zeros(NUM_OCC3D_CLASSES, NUM_OCC3D_CLASSES, dtype=torch.int64)

    def update(
        self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None
    ) -> None:
        """Add one batch ([...] class ids, optional bool mask)."""
        self.conf += confusion_matrix(pred, target, mask)

    def compute(self) -> dict[str, float | list[float]]:
        """Scores of everything accumulated so far."""
        return metrics_from_confusion(self.conf)
