"""Reconstruction metrics of a tokenizer (OccWorld protocol, docs/protocol.md).

An 18x18 confusion matrix (rows: ground truth, columns: prediction) is accumulated over all
frames; per-class IoU = TP / (TP + FP + FN); mIoU is the mean over the non-air classes 0..16
of the classes with a non-empty union (free stays in the confusion but not in the mean); the
geometry IoU scores occupied (any non-air class) vs free. By default the full volume is scored;
pass ``mask`` (e.g. Occ3D's camera mask) to score only those voxels and label it as such.

This is a small local helper for the tokenizer's tests and fitting; the package-wide metrics
live in ``renderworld.metrics``.
"""

from __future__ import annotations

import torch

from renderworld.constants import NUM_OCC3D_CLASSES
from renderworld.metrics.occupancy import geometry_iou, iou_per_class, mean_iou

__all__ = ["confusion_matrix", "metrics_from_confusion", "reconstruction_metrics", "ConfusionMeter"]


def _check_labels(name: str, x: torch.Tensor) -> None:
    if x.dtype.is_floating_point or x.dtype == torch.bool:
        raise TypeError(f"{name}: expected an integer tensor of class ids, got {x.dtype}")
    if x.numel() and (int(x.min()) < 0 or int(x.max()) >= NUM_OCC3D_CLASSES):
        raise ValueError(
            f"{name}: expected class ids in [0, {NUM_OCC3D_CLASSES - 1}], "
            f"got range [{int(x.min())}, {int(x.max())}]"
        )


def confusion_matrix(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """18x18 confusion of one batch.

    Args:
        pred: [...] integer predicted Occ3D ids.
        target: [...] integer true Occ3D ids, same shape.
        mask: Optional [...] bool, voxels to score.

    Returns:
        [18, 18] int64, ``conf[t, p]`` = voxels of true class t predicted as p.
    """
    if pred.shape != target.shape:
        raise ValueError(
            f"pred: expected the shape of target {tuple(target.shape)}, got {tuple(pred.shape)}"
        )
    _check_labels("pred", pred)
    _check_labels("target", target)
    p, t = pred.reshape(-1).long(), target.reshape(-1).long()
    if mask is not None:
        if mask.shape != target.shape or mask.dtype != torch.bool:
            raise ValueError(
                f"mask: expected bool of shape {tuple(target.shape)}, "
                f"got {mask.dtype} {tuple(mask.shape)}"
            )
        keep = mask.reshape(-1)
        p, t = p[keep], t[keep]
    n = NUM_OCC3D_CLASSES
    return torch.bincount(t * n + p, minlength=n * n).reshape(n, n).cpu()


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
