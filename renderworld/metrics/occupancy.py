"""Semantic occupancy metrics: confusion matrix, IoU per class, mIoU, geometry IoU.

Protocol (docs/protocol.md#occupancy, Occ3D official): an 18x18 confusion matrix (rows = ground
truth, columns = prediction) is **summed over the whole split** (never per-sample IoUs averaged);
IoU_c = TP / (TP + FP + FN); mIoU = nanmean of IoU over classes 0..16 (free = 17 is excluded
from the mean but its voxels stay in the confusion, so predicting free where an object is counts
as a false negative of that object); a class with no GT and no prediction voxel has IoU NaN and
is left out of the mean. Geometry IoU treats classes 0..16 as occupied and free as empty.
The region is either the full volume (OccWorld protocol for tokenizer reconstruction and
forecasting) or voxels inside a mask (e.g. the Occ3D camera mask), and is named in the output.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES, OCC3D_CLASSES

__all__ = [
    "OCCUPANCY_PROTOCOL",
    "OccupancyMetric",
    "confusion_matrix",
    "geometry_iou",
    "iou_per_class",
    "mean_iou",
]

OCCUPANCY_PROTOCOL = (
    "18x18 confusion summed over the split; IoU per class; mIoU = nanmean over classes 0..16 "
    "(free excluded from the mean, kept in the confusion); geometry IoU = occupied (0..16) vs free"
)


def _to_numpy(x, name: str) -> np.ndarray:
    if isinstance(x, np.ndarray):
        return x
    try:  # torch tensor (any device) without importing torch here
        return x.detach().cpu().numpy()
    except AttributeError:
        raise TypeError(
            f"{name}: expected a numpy array or torch tensor, got {type(x).__name__}"
        ) from None


def confusion_matrix(pred, gt, mask=None, num_classes: int = NUM_OCC3D_CLASSES) -> np.ndarray:
    """Confusion counts of one batch.

    Args:
        pred: [...] integer labels in [0, num_classes) (any shape, e.g. [B, X, Y, Z]).
        gt: same shape as ``pred``.
        mask: same shape, bool (or 0/1); only voxels where it is True count. None = all.
        num_classes: K (18 for Occ3D).

    Returns:
        [K, K] int64, ``out[g, p]`` = number of voxels with GT ``g`` predicted as ``p``.

    Raises:
        ValueError: shape mismatch, non-integer labels, labels outside [0, K).
    """
    p = _to_numpy(pred, "pred")
    g = _to_numpy(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred: expected the shape of gt {g.shape}, got {p.shape}")
    for name, arr in (("pred", p), ("gt", g)):
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{name}: expected integer class labels, got dtype {arr.dtype}")
        if arr.size and (int(arr.min()) < 0 or int(arr.max()) >= num_classes):
            raise ValueError(
                f"{name}: expected labels in [0, {num_classes - 1}], got "
                f"[{int(arr.min())}, {int(arr.max())}]"
            )
    if mask is not None:
        m = _to_numpy(mask, "mask")
        if m.shape != g.shape:
            raise ValueError(f"mask: expected the shape of gt {g.shape}, got {m.shape}")
        if m.dtype != np.bool_:
            if not np.isin(m, (0, 1)).all():
                raise ValueError("mask: expected bool or 0/1 values")
            m = m.astype(bool)
        p, g = p[m], g[m]
    idx = g.astype(np.int64).ravel() * num_classes + p.astype(np.int64).ravel()
    return np.bincount(idx, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def _check_confusion(confusion: np.ndarray) -> np.ndarray:
    c = np.asarray(confusion)
    if c.ndim != 2 or c.shape[0] != c.shape[1]:
        raise ValueError(f"confusion: expected a square [K, K] matrix, got {c.shape}")
    return c.astype(np.float64)


def iou_per_class(confusion: np.ndarray) -> np.ndarray:
    """IoU of every class from a confusion matrix.

    Args:
        confusion: [K, K] counts (rows GT, columns prediction).

    Returns:
        [K] float64; NaN where the class has neither GT nor predicted voxels (union 0).
    """
    c = _check_confusion(confusion)
    tp = np.diag(c)
    union = c.sum(0) + c.sum(1) - tp
    out = np.full(c.shape[0], np.nan)
    np.divide(tp, union, out=out, where=union > 0)
    return out


def mean_iou(confusion: np.ndarray, free_id: int = FREE_ID) -> float:
    """mIoU = nanmean of IoU over every class but ``free_id`` (classes 0..16 for Occ3D).

    Returns NaN when no such class has a GT or predicted voxel.
    """
    iou = np.delete(iou_per_class(confusion), free_id)
    present = ~np.isnan(iou)
    return float(iou[present].mean()) if present.any() else float("nan")


def geometry_iou(confusion: np.ndarray, free_id: int = FREE_ID) -> float:
    """IoU of occupied (every class but ``free_id``) vs free; NaN when nothing is occupied."""
    c = _check_confusion(confusion)
    occ = np.ones(c.shape[0], dtype=bool)
    occ[free_id] = False
    tp = c[np.ix_(occ, occ)].sum()
    fp = c[free_id, occ].sum()
    fn = c[occ, free_id].sum()
    union = tp + fp + fn
    return float(tp / union) if union > 0 else float("nan")


class OccupancyMetric:
    """Accumulates a confusion matrix over a split (Occ3D protocol, see module docstring).

    Args:
        mask_name: None for the full volume (then ``update`` refuses a mask), or the name of the
            mask every ``update`` must pass (e.g. ``"camera"``); recorded in the output so a
            full-volume and a masked number are never confused.
        class_names: names of the K classes (default Occ3D, K = 18; free last).

    Example:
        >>> m = OccupancyMetric(mask_name="camera")
        >>> m.update(pred, gt, mask=mask_camera)   # doctest: +SKIP
        >>> m.compute()["miou"]                    # doctest: +SKIP
    """

    def __init__(self, mask_name: str | None = None, class_names=OCC3D_CLASSES):
        if mask_name is not None and (not isinstance(mask_name, str) or not mask_name):
            raise ValueError(f"mask_name: expected None or a non-empty str, got {mask_name!r}")
        self.mask_name = mask_name
        self.class_names = tuple(class_names)
        k = len(self.class_names)
        self.free_id = self.class_names.index("free") if "free" in self.class_names else FREE_ID
        self.confusion = np.zeros((k, k), dtype=np.int64)
        self.num_updates = 0

    @property
    def region(self) -> str:
        """Human-readable region the metric is computed over."""
        return "full volume" if self.mask_name is None else f"inside the {self.mask_name} mask"

    def reset(self) -> None:
        """Zero the accumulated counts."""
        self.confusion[:] = 0
        self.num_updates = 0

    def update(self, pred, gt, mask=None) -> None:
        """Add a batch: ``pred``/``gt`` [...] labels, ``mask`` [...] bool (see ``mask_name``)."""
        if self.mask_name is None and mask is not None:
            raise ValueError(
                "mask: this metric is over the full volume (mask_name=None); create "
                "OccupancyMetric(mask_name=...) for masked evaluation"
            )
        if self.mask_name is not None and mask is None:
            raise ValueError(f"mask: expected the {self.mask_name!r} mask, got None")
        self.confusion += confusion_matrix(pred, gt, mask, num_classes=len(self.class_names))
        self.num_updates += 1

    def merge(self, other: OccupancyMetric) -> OccupancyMetric:
        """Add another accumulator's counts (e.g. from another process); returns self."""
        if not isinstance(other, OccupancyMetric):
            raise TypeError(f"other: expected OccupancyMetric, got {type(other).__name__}")
        if other.mask_name != self.mask_name or other.class_names != self.class_names:
            raise ValueError(
                f"other: cannot merge region {other.region!r} into {self.region!r} "
                "(or different classes)"
            )
        self.confusion += other.confusion
        self.num_updates += other.num_updates
        return self

    def compute(self) -> dict:
        """Metrics of everything accumulated so far.

        Returns:
            dict: ``miou`` (classes 0..16, nanmean), ``iou_geometry``, ``iou_per_class``
            {name: IoU or NaN} (free included for reference), ``num_voxels``, ``region``,
            ``protocol``.
        """
        iou = iou_per_class(self.confusion)
        return {
            "miou": mean_iou(self.confusion, self.free_id),
            "iou_geometry": geometry_iou(self.confusion, self.free_id),
            "iou_per_class": dict(zip(self.class_names, iou.tolist())),
            "num_voxels": int(self.confusion.sum()),
            "region": self.region,
            "protocol": OCCUPANCY_PROTOCOL,
        }

    def format_table(self) -> str:
        """A printable table whose header states the protocol and the region."""
        r = self.compute()
        lines = [
            f"# Occupancy ({r['region']}): {OCCUPANCY_PROTOCOL}",
            f"{'class':<22}{'IoU %':>8}",
        ]
        for name, v in r["iou_per_class"].items():
            lines.append(f"{name:<22}{100 * v:>8.2f}")
        lines.append(f"{'mIoU (0..16)':<22}{100 * r['miou']:>8.2f}")
        lines.append(f"{'IoU geometry':<22}{100 * r['iou_geometry']:>8.2f}")
        return "\n".join(lines)
