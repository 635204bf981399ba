"""Readout calibration: per-class logit offsets chosen with the per-class thresholds.

The readout gives a voxel the class ``argmax(logits + offsets)`` and occupies it when its
opacity exceeds that class's threshold. The per-class thresholds alone cannot undo a class
that wins the argmax too often (rare classes trained with class-balanced losses claim road and
free voxels: with the img2occ_mini model of d869d89, 256 driveable voxels of mini_val read as
barrier against 98 true barrier voxels), so :class:`ReadoutCalibration` also chooses one
additive logit offset per class, on the same GT-labelled training samples and the same
criterion (Occ3D mIoU over the camera mask). Coordinate ascent: each class's offset in turn
takes the candidate that maximises the mIoU with the others fixed (ties keep the current one,
0 at the start), then the per-class thresholds are re-chosen for the new argmax; ``rounds``
passes.

Memory: voxels whose opacity is at or below the smallest candidate threshold read as free
whatever the offsets, so only their (GT, free) counts are kept; the others are stored
(80 bytes per voxel: 17 float32 logits, the opacity, the int64 GT id): measured 373,188 of
431,166 camera-visible voxels, 28.5 MiB, for the 96 samples of ``experiment=img2occ_mini``; the
fit took 5.2 s there. On large grids cap the samples (``stage.threshold.max_samples``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.metrics.occupancy import confusion_counts, iou_per_class, mean_iou

__all__ = ["DEFAULT_OFFSETS", "ReadoutCalibration", "readout_classes"]

#: Candidate logit offsets per class.
DEFAULT_OFFSETS: tuple[float, ...] = (-3, -2, -1.5, -1, -0.5, -0.25, 0, 0.25, 0.5, 1, 1.5, 2, 3)

_N = NUM_OCC3D_CLASSES  # 18: classes 0..16 and FREE_ID 17


def readout_classes(logits: torch.Tensor, offsets: torch.Tensor | None = None) -> torch.Tensor:
    """Voxel classes ``argmax(logits + offsets)`` over the last dim (offsets [K] or None)."""
    if offsets is None:
        return logits.argmax(-1)
    return (logits + offsets.to(logits)).argmax(-1)


def _miou(conf: torch.Tensor) -> float:
    return mean_iou(conf.numpy())  # nanmean over classes 0..16, the metric's own protocol


class ReadoutCalibration:
    """Accumulates labelled voxels, then fits per-class logit offsets and thresholds.

    Args:
        thresholds: candidate opacity thresholds in [0, 1).
        offsets: candidate logit offsets (must include 0, the start).
        rounds: coordinate-ascent passes over the classes.
    """

    def __init__(
        self,
        thresholds: Sequence[float],
        offsets: Sequence[float] = DEFAULT_OFFSETS,
        rounds: int = 2,
    ) -> None:
        self.thresholds = torch.as_tensor(sorted(thresholds), dtype=torch.float32)
        if self.thresholds.ndim != 1 or self.thresholds.numel() == 0:
            raise ValueError(f"thresholds: expected a non-empty list, got {list(thresholds)}")
        if bool(((self.thresholds < 0) | (self.thresholds >= 1)).any()):
            raise ValueError(f"thresholds: expected values in [0, 1), got {list(thresholds)}")
        self.offsets = [float(o) for o in offsets]
        if 0.0 not in self.offsets or not all(np.isfinite(self.offsets)):
            raise ValueError(f"offsets: expected finite candidates including 0, got {offsets}")
        if int(rounds) < 1:
            raise ValueError(f"rounds: expected an integer >= 1, got {rounds!r}")
        self.rounds = int(rounds)
        self.floor = float(self.thresholds.min())
        self.base = torch.zeros(_N, _N, dtype=torch.float64)  # always-free voxels
        self._op: list[torch.Tensor] = []
        self._logits: list[torch.Tensor] = []
        self._gt: list[torch.Tensor] = []

    @torch.no_grad()
    def update(self, opacities, logits, gt, mask=None) -> None:
        """Add one batch: opacities [B, V], logits [B, V, K], GT ids [B, V] (or [B, X, Y, Z]
        reshaped alike), mask bool of the voxels that count (camera mask) or None."""
        op = torch.as_tensor(opacities).detach().reshape(-1).float().cpu()
        lg = torch.as_tensor(logits).detach().cpu()
        lg = lg.reshape(-1, lg.shape[-1])
        gt = torch.as_tensor(gt).reshape(-1).long().cpu()
        if not (op.numel() == lg.shape[0] == gt.numel()) or lg.shape[-1] != FREE_ID:
            raise ValueError(
                f"opacities/logits/gt: expected V, [V, {FREE_ID}], V voxels, got {op.numel()}, "
                f"{tuple(lg.shape)}, {gt.numel()}"
            )
        if mask is not None:
            m = torch.as_tensor(mask).reshape(-1).bool().cpu()
            op, lg, gt = op[m], lg[m], gt[m]
        live = op > self.floor
        dead = gt[~live]  # read as free whatever the offsets and thresholds
        self.base += confusion_counts(torch.full_like(dead, FREE_ID), dead, names=("readout", "gt"))
        self._op.append(op[live])
        self._logits.append(lg[live].float())
        self._gt.append(gt[live])

    def _data(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if not self._op:
            raise ValueError("ReadoutCalibration: no batch was added")
        return torch.cat(self._op), torch.cat(self._logits), torch.cat(self._gt)

    def confusion(self, offsets: torch.Tensor, thresholds: torch.Tensor, data=None):
        """[18, 18] float64 confusion (rows GT) of the readout with these [K] offsets and
        [K] thresholds over everything added."""
        op, lg, gt = data if data is not None else self._data()
        cls = readout_classes(lg, offsets)
        pred = torch.where(op > thresholds[cls], cls, torch.full_like(cls, FREE_ID))
        return confusion_counts(pred, gt, names=("readout", "gt")).double() + self.base

    def _best_thresholds(self, offsets: torch.Tensor, data) -> torch.Tensor:
        """Per class, the candidate maximising that class's IoU for this argmax. A class
        with no GT voxel scores best where it is never predicted (IoU NaN, left out of the
        mean) rather than at IoU 0; ties take the lowest threshold."""
        scores = np.stack(
            [
                iou_per_class(self.confusion(offsets, t.expand(FREE_ID), data).numpy())[:FREE_ID]
                for t in self.thresholds
            ]
        )  # [T, K]
        best = np.nan_to_num(scores, nan=2.0).argmax(0)  # first maximum: lowest threshold
        return self.thresholds[torch.as_tensor(best)]

    def fit(self) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
        """Choose the offsets and thresholds.

        Returns:
            ``(offsets [K], thresholds [K], history)``: float32 tensors and the mIoU after
            the thresholds-only start and after each round (non-decreasing).
        """
        data = self._data()
        offsets = torch.zeros(FREE_ID)
        thresholds = self._best_thresholds(offsets, data)
        current = _miou(self.confusion(offsets, thresholds, data))
        history = [current]
        for _ in range(self.rounds):
            for k in range(FREE_ID):
                for cand in self.offsets:
                    if cand == float(offsets[k]):
                        continue
                    trial = offsets.clone()
                    trial[k] = cand
                    value = _miou(self.confusion(trial, thresholds, data))
                    if value > current + 1e-9:
                        current, offsets = value, trial
            # A class's IoU depends on its own threshold only, for a fixed argmax: re-choosing
            # them per class never lowers the mIoU.
            thresholds = self._best_thresholds(offsets, data)
            current = _miou(self.confusion(offsets, thresholds, data))
            history.append(current)
        return offsets, thresholds, history
