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

import sys

import numpy as np

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES, OCC3D_CLASSES

__all__ = [
    "OCCUPANCY_PROTOCOL",
    "OccupancyMetric",
    "confusion_counts",
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


def _torch_if_tensors(*arrays):
    """The torch module when every given (non-None) array is a torch tensor, else None."""
    torch = sys.modules.get("torch")
    given = [a for a in arrays if a is not None]
    if torch is not None and all(isinstance(a, torch.Tensor) for a in given):
        return torch
    return None


def _label_range_error(arrays, names, num_classes: int) -> ValueError | None:
    """The ValueError naming the first label array with a value outside [0, K), else None."""
    for name, arr in zip(names, arrays):
        if arr.size and (int(arr.min()) < 0 or int(arr.max()) >= num_classes):
            return ValueError(
                f"{name}: expected labels in [0, {num_classes - 1}], got "
                f"[{int(arr.min())}, {int(arr.max())}]"
            )
    return None


def confusion_counts(
    pred,
    gt,
    mask=None,
    num_classes: int = NUM_OCC3D_CLASSES,
    *,
    names: tuple[str, str] = ("pred", "gt"),
):
    """Confusion counts of one batch in the inputs' own array library.

    The package's one counting rule: every confusion (metrics, tokenizer, training stages,
    readout calibration) comes from here. Torch tensors are counted by one ``torch.bincount``
    on their device and stay there; anything else is counted by ``np.bincount``. The label
    check is folded into the counted index (an invalid voxel gets index -1, which bincount
    refuses), so a CUDA batch adds no host synchronisation beyond bincount's own.

    Args:
        pred: [...] integer labels in [0, num_classes) (any shape, e.g. [B, X, Y, Z]).
        gt: same shape as ``pred``.
        mask: same shape, bool or integer 0/1; only voxels where it is true count. None = all.
        num_classes: K (18 for Occ3D).
        names: the names of ``pred`` and ``gt`` in the caller's signature, used in errors.

    Returns:
        [K, K] int64 (a torch tensor on the inputs' device when all inputs are tensors, else a
        numpy array), ``out[g, p]`` = number of voxels with GT ``g`` predicted as ``p``.

    Raises:
        ValueError: shape mismatch, non-integer labels, labels outside [0, K) anywhere (masked
            voxels included), a mask that is not bool or 0/1.
    """
    torch = _torch_if_tensors(pred, gt, mask)
    if torch is None:
        pred, gt = _to_numpy(pred, names[0]), _to_numpy(gt, names[1])
        mask = None if mask is None else _to_numpy(mask, "mask")
    if pred.shape != gt.shape:
        raise ValueError(
            f"{names[0]}: expected the shape of {names[1]} {tuple(gt.shape)}, "
            f"got {tuple(pred.shape)}"
        )
    for name, arr in zip(names, (pred, gt)):
        if not _is_integer(arr, torch):
            raise ValueError(f"{name}: expected integer class labels, got dtype {arr.dtype}")
    if mask is not None and (
        tuple(mask.shape) != tuple(gt.shape)
        or not (_is_bool(mask, torch) or _is_integer(mask, torch))
    ):
        raise ValueError(
            f"mask: expected bool or 0/1 values of shape {tuple(gt.shape)}, "
            f"got {mask.dtype} {tuple(mask.shape)}"
        )
    n = int(num_classes)
    xp = np if torch is None else torch
    p = _as_int64(pred.reshape(-1), torch)
    g = _as_int64(gt.reshape(-1), torch)
    invalid = (p < 0) | (p >= n) | (g < 0) | (g >= n)
    idx = g * n + p
    if mask is not None:
        m = mask.reshape(-1)
        if not _is_bool(mask, torch):
            invalid = invalid | ((m != 0) & (m != 1))
            m = m != 0
        idx = xp.where(m, idx, n * n)  # masked-out voxels go to a spare bin
    idx = xp.where(invalid, -1, idx)
    try:
        counts = xp.bincount(idx, minlength=n * n + 1)
    except (RuntimeError, ValueError) as err:  # bincount refuses the -1 of an invalid voxel
        cpu = [_to_numpy(a, nm) for a, nm in zip((pred, gt), names)]
        range_error = _label_range_error(cpu, names, n)
        if range_error is not None:
            raise range_error from None
        if mask is not None:
            raise ValueError("mask: expected bool or 0/1 values") from None
        raise err
    return counts[: n * n].reshape(n, n)


def _is_integer(arr, torch) -> bool:
    if torch is None:
        return np.issubdtype(arr.dtype, np.integer)
    return not (arr.dtype.is_floating_point or arr.dtype.is_complex or arr.dtype == torch.bool)


def _is_bool(arr, torch) -> bool:
    return arr.dtype == (np.bool_ if torch is None else torch.bool)


def _as_int64(arr, torch):
    return arr.astype(np.int64, copy=False) if torch is None else arr.long()


def confusion_matrix(pred, gt, mask=None, num_classes: int = NUM_OCC3D_CLASSES) -> np.ndarray:
    """Confusion counts of one batch as a numpy array (see :func:`confusion_counts`).

    Args:
        pred: [...] integer labels in [0, num_classes) (numpy or torch, any shape).
        gt: same shape as ``pred``.
        mask: same shape, bool (or 0/1); only voxels where it is True count. None = all.
        num_classes: K (18 for Occ3D).

    Returns:
        [K, K] int64 numpy, ``out[g, p]`` = number of voxels with GT ``g`` predicted as ``p``.

    Raises:
        ValueError: shape mismatch, non-integer labels, labels outside [0, K).
    """
    return _to_numpy(confusion_counts(pred, gt, mask, num_classes), "confusion")


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
