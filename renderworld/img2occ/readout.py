"""Readout threshold: pick the opacity threshold that maximises training-split mIoU.

A voxel is occupied when its Gaussian's opacity exceeds the threshold, its class is the argmax
of the logits. ``choose_threshold`` runs the model over GT-labelled batches, accumulates one
18x18 confusion matrix per candidate threshold (Occ3D protocol: camera mask applied, whole
split accumulated, mIoU = nanmean of the IoUs of classes 0..16) and stores the best threshold
in the model's ``occupancy_threshold`` buffer, so it is saved with the checkpoint.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.img2occ.calibration import DEFAULT_OFFSETS, ReadoutCalibration, readout_classes
from renderworld.metrics.occupancy import confusion_matrix as occupancy_confusion
from renderworld.metrics.occupancy import geometry_iou, iou_per_class, mean_iou

__all__ = [
    "DEFAULT_THRESHOLDS",
    "ThresholdSearch",
    "choose_threshold",
    "confusion_matrix",
    "miou_from_confusion",
    "geometry_iou_from_confusion",
    "readout_occupancy",
]

#: Candidate opacity thresholds searched by default.
DEFAULT_THRESHOLDS: tuple[float, ...] = tuple(np.round(np.arange(0.05, 0.96, 0.05), 2).tolist())


def confusion_matrix(pred, gt, mask=None) -> np.ndarray:
    """18x18 confusion (rows GT, columns prediction) over Occ3D ids 0..17.

    Args:
        pred: [...] predicted ids 0..17 (numpy or torch).
        gt: [...] GT ids 0..17, same shape.
        mask: [...] bool voxels to count (e.g. the camera mask); all when None.

    Returns:
        [18, 18] int64.
    """
    return occupancy_confusion(pred, gt, mask).astype(np.int64)


def miou_from_confusion(conf: np.ndarray) -> tuple[float, np.ndarray]:
    """(mIoU, per-class IoU [18]) from an 18x18 confusion; nanmean over classes 0..16.

    A class absent from both GT and prediction has IoU NaN and is left out of the mean
    (the Occ3D protocol of :mod:`renderworld.metrics.occupancy`, which computes it).
    """
    return mean_iou(conf), iou_per_class(conf)


def geometry_iou_from_confusion(conf: np.ndarray) -> float:
    """IoU of occupied (any class 0..16) vs free from an 18x18 confusion."""
    return geometry_iou(conf)


class ThresholdSearch:
    """Streaming confusion matrices for a set of candidate opacity thresholds.

    Args:
        thresholds: candidate thresholds in [0, 1).
    """

    def __init__(self, thresholds: Sequence[float] = DEFAULT_THRESHOLDS):
        th = np.asarray(list(thresholds), dtype=np.float64)
        if th.ndim != 1 or th.size == 0 or (th < 0).any() or (th >= 1).any():
            raise ValueError(f"thresholds: expected values in [0, 1), got {list(thresholds)}")
        self.thresholds = th
        self.conf = np.zeros((th.size, NUM_OCC3D_CLASSES, NUM_OCC3D_CLASSES), dtype=np.int64)

    def update(self, opacities, classes, gt, mask=None) -> None:
        """Add one batch.

        Args:
            opacities: [B, X, Y, Z] (or [B, V]) Gaussian opacities.
            classes: same shape, argmax class 0..16 of each voxel.
            gt: same shape, GT ids 0..17.
            mask: same shape bool, voxels that count (camera mask), or None.
        """
        op = torch.as_tensor(opacities).detach().reshape(-1)
        cls = torch.as_tensor(classes).reshape(-1).long().to(op.device)
        gt = torch.as_tensor(gt).reshape(-1).to(op.device)
        if not (op.shape == cls.shape == gt.shape):
            raise ValueError(
                f"opacities/classes/gt: expected equal sizes, got {op.numel()}, {cls.numel()}, "
                f"{gt.numel()}"
            )
        if mask is not None:
            m = torch.as_tensor(mask).reshape(-1).bool().to(op.device)
            op, cls, gt = op[m], cls[m], gt[m]
        free = torch.full_like(cls, FREE_ID)
        for i, t in enumerate(self.thresholds):
            self.conf[i] += confusion_matrix(torch.where(op > float(t), cls, free), gt)

    def scores(self, criterion: str = "miou") -> np.ndarray:
        """Score per threshold: ``"miou"`` (classes 0..16) or ``"iou"`` (geometry)."""
        if criterion == "miou":
            return np.array([miou_from_confusion(c)[0] for c in self.conf])
        if criterion == "iou":
            return np.array([geometry_iou_from_confusion(c) for c in self.conf])
        raise ValueError(f"criterion: expected 'miou' or 'iou', got {criterion!r}")

    def best_per_class(self) -> np.ndarray:
        """[K] thresholds, one per class 0..16, each maximising that class's IoU.

        A class's IoU depends only on which voxels read as that class, i.e. on its own
        threshold, so choosing each one on its own maximises the mIoU over all per-class
        choices among the candidates. Ties take the lowest threshold; a class absent from
        the accumulated GT and predictions gets the single best-mIoU threshold.
        """
        fallback = self.best("miou")
        ious = np.stack([miou_from_confusion(c)[1][:FREE_ID] for c in self.conf])  # [T, K]
        out = np.full(FREE_ID, fallback)
        for k in range(FREE_ID):
            if np.isfinite(ious[:, k]).any():
                out[k] = self.thresholds[int(np.nanargmax(ious[:, k]))]
        return out

    def best(self, criterion: str = "miou") -> float:
        """The threshold with the highest score (the lowest one on ties; NaN scores lose)."""
        s = self.scores(criterion)
        if not np.isfinite(s).any():
            raise ValueError("best: no finite score; was any voxel with GT accumulated?")
        return float(self.thresholds[int(np.nanargmax(s))])


@torch.no_grad()
def choose_threshold(
    model,
    batches: Iterable[dict],
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    criterion: str = "miou",
    use_camera_mask: bool = True,
    per_class: bool = False,
    class_offsets: bool = False,
    offset_candidates: Sequence[float] = DEFAULT_OFFSETS,
    offset_rounds: int = 2,
) -> tuple[float, dict[float, float]]:
    """Pick the readout threshold maximising training-split mIoU and store it in ``model``.

    Args:
        model: an :class:`~renderworld.img2occ.Img2Occ`.
        batches: iterable of batches (training split) holding ``occ`` [B, X, Y, Z] GT and,
            with ``use_camera_mask``, ``mask_camera``; tensors on the model's device.
        thresholds: candidates.
        criterion: ``"miou"`` (default, Occ3D mIoU over 0..16) or ``"iou"`` (geometry).
        use_camera_mask: count only camera-visible voxels (Occ3D protocol).
        per_class: also choose one threshold per class (:meth:`ThresholdSearch.
            best_per_class`, needs criterion "miou") and store them in
            ``model.class_thresholds``; the returned threshold is then the single best one.
        class_offsets: also choose per-class logit offsets together with the per-class
            thresholds (:class:`~renderworld.img2occ.calibration.ReadoutCalibration`, needs
            per_class) and store them in ``model.class_offsets``; the model's offsets are
            reset to 0 first. Without it the model's stored offsets apply as they are.
        offset_candidates: candidate offsets (with class_offsets).
        offset_rounds: coordinate-ascent passes (with class_offsets).

    Returns:
        ``(threshold, {threshold: score})``; the threshold is also written to
        ``model.occupancy_threshold``.
    """
    if class_offsets and not per_class:
        raise ValueError("class_offsets: needs per_class (offsets and thresholds go together)")
    if per_class and criterion != "miou":
        raise ValueError("per_class: needs criterion 'miou' (geometry IoU is not per class)")
    search = ThresholdSearch(thresholds)
    calibration = None
    if class_offsets:
        calibration = ReadoutCalibration(thresholds, offset_candidates, offset_rounds)
        model.set_class_offsets(torch.zeros_like(model.class_offsets))
    was_training = model.training
    model.eval()
    seen = 0
    try:
        for batch in batches:
            if "occ" not in batch:
                raise ValueError("batches: every batch needs GT 'occ' to choose a threshold")
            if use_camera_mask and "mask_camera" not in batch:
                raise ValueError("batches: 'mask_camera' missing (or pass use_camera_mask=False)")
            out = model(batch, render=False)
            g = out.gaussians
            mask = batch["mask_camera"] if use_camera_mask else None
            search.update(
                g.opacities, readout_classes(g.logits, model.class_offsets), batch["occ"], mask
            )
            if calibration is not None:
                calibration.update(g.opacities, g.logits, batch["occ"], mask)
            seen += 1
    finally:
        model.train(was_training)
    if seen == 0:
        raise ValueError("batches: empty; expected at least one batch with GT")
    best = search.best(criterion)
    model.set_threshold(best)
    if calibration is not None:
        offsets, per_class_thresholds, _ = calibration.fit()
        model.set_class_offsets(offsets)
        model.set_class_thresholds(per_class_thresholds)
    elif per_class:
        model.set_class_thresholds(search.best_per_class())
    scores = search.scores(criterion)
    return best, {float(t): float(s) for t, s in zip(search.thresholds, scores)}


def readout_occupancy(
    opacities: torch.Tensor, logits: torch.Tensor, threshold, grid_shape, offsets=None
):
    """Voxel classes: argmax of logits (+ offsets) where opacity > threshold, else ``FREE_ID``.

    Args:
        opacities: [B, V] in (0, 1).
        logits: [B, V, K].
        threshold: opacity threshold, a float or a [K] tensor of per-class thresholds (the
            one of each voxel's argmax class applies).
        grid_shape: (X, Y, Z) with X·Y·Z = V.
        offsets: [K] per-class logit offsets added before the argmax
            (:mod:`renderworld.img2occ.calibration`), or None.

    Returns:
        [B, X, Y, Z] uint8 Occ3D ids (``FREE_ID`` = free).
    """
    cls = readout_classes(logits, offsets)
    if isinstance(threshold, torch.Tensor) and threshold.ndim == 1:
        threshold = threshold.to(opacities)[cls]
    out = torch.where(opacities > threshold, cls, torch.full_like(cls, FREE_ID))
    return out.to(torch.uint8).view(opacities.shape[0], *grid_shape)
