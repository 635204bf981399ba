"""Occupancy forecasting metrics at 1 s / 2 s / 3 s.

Protocol (OccWorld; docs/protocol.md#tokenizer-reconstruction-and-forecasts): one confusion matrix
per future step, each summed over the split (:mod:`renderworld.metrics.occupancy`);
"1 s / 2 s / 3 s" are the values at steps 2 / 4 / 6 (keyframes every 0.5 s), never averaged over
the steps in between; the ``avg`` column is the plain mean of the three horizon values (as
OccWorld reports it). Region: full volume by default, or inside a named mask. Future frames past
the end of a scene (``valid`` False) are excluded and counted in ``skipped_frames``.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import FUTURE_FRAMES, KEYFRAME_DT, MOVABLE_CLASS_IDS
from renderworld.metrics.occupancy import (
    OCCUPANCY_PROTOCOL,
    OccupancyMetric,
    _to_numpy,
    iou_per_class,
)

__all__ = [
    "FORECAST_HORIZONS_S",
    "ForecastMetric",
    "checked_horizons",
    "horizon_steps",
    "movers_miou",
]

FORECAST_HORIZONS_S: tuple[float, ...] = (1.0, 2.0, 3.0)


def movers_miou(confusion) -> float:
    """Movers' mIoU: nanmean of the IoU of the movable classes (``MOVABLE_CLASS_IDS``).

    Read off the same confusion as the mIoU (a class with no GT and no prediction voxel is
    left out of the mean, as in :func:`~renderworld.metrics.occupancy.mean_iou`).

    Args:
        confusion: [18, 18] counts, rows = ground truth.

    Returns:
        The mean as a fraction, NaN when no movable class is present.
    """
    iou = iou_per_class(confusion)[list(MOVABLE_CLASS_IDS)]
    present = ~np.isnan(iou)
    return float(iou[present].mean()) if present.any() else float("nan")


def horizon_steps(horizons_s=FORECAST_HORIZONS_S, dt: float = KEYFRAME_DT) -> tuple[int, ...]:
    """Step index (1-based) of each horizon: 1 s -> 2, 2 s -> 4, 3 s -> 6 at 2 Hz."""
    steps = []
    for h in horizons_s:
        k = round(h / dt)
        if k < 1 or abs(k * dt - h) > 1e-6:
            raise ValueError(f"horizons_s: {h} s is not a positive multiple of {dt} s")
        steps.append(k)
    return tuple(steps)


def checked_horizons(steps: int, horizons_s) -> tuple[tuple[float, ...], tuple[int, ...]]:
    """Validate a rollout length and its reporting horizons.

    Returns:
        (horizons in seconds, their 1-based step indices).

    Raises:
        ValueError: ``steps`` is not an int >= 1, or a horizon is off the step grid or beyond it.
    """
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    hs = tuple(float(h) for h in horizons_s)
    ks = horizon_steps(hs)
    if max(ks) > steps:
        raise ValueError(f"horizons_s: {hs} need more than {steps} steps")
    return hs, ks


class ForecastMetric:
    """Accumulates per-step occupancy confusions of forecasts over a split.

    Args:
        steps: S future frames per forecast (6 = 3 s).
        horizons_s: reported horizons in seconds (each must map to a step <= S).
        mask_name: None (full volume) or the name of the mask every update passes.
    """

    def __init__(
        self,
        steps: int = FUTURE_FRAMES,
        horizons_s=FORECAST_HORIZONS_S,
        mask_name: str | None = None,
    ):
        self.steps = steps
        self.horizons_s, self.horizon_steps = checked_horizons(steps, horizons_s)
        self.mask_name = mask_name
        self.per_step = [OccupancyMetric(mask_name=mask_name) for _ in range(steps)]
        self.skipped_frames = 0

    def update(self, pred, gt, mask=None, valid=None) -> None:
        """Add forecasts.

        Args:
            pred: [S, X, Y, Z] or [B, S, X, Y, Z] predicted labels of frames t+1..t+S.
            gt: same shape, ground truth (each frame in its own ego frame, like ``pred``).
            mask: same shape bool, or None (must match ``mask_name``).
            valid: [S] or [B, S] bool, False for frames past the scene end; None = all valid.
        """
        p, g = _to_numpy(pred, "pred"), _to_numpy(gt, "gt")
        if p.ndim == 4:  # one forecast without a batch axis
            p = p[None]
            g = g[None] if g.ndim == 4 else g
            mask = None if mask is None else _to_numpy(mask, "mask")[None]
            valid = None if valid is None else _to_numpy(valid, "valid")[None]
        if p.ndim != 5 or p.shape[1] != self.steps:
            raise ValueError(
                f"pred: expected [S={self.steps}, X, Y, Z] or [B, {self.steps}, X, Y, Z], "
                f"got {p.shape}"
            )
        if g.shape != p.shape:
            raise ValueError(f"gt: expected shape {p.shape}, got {g.shape}")
        m = None if mask is None else _to_numpy(mask, "mask")
        if valid is None:
            v = np.ones(p.shape[:2], dtype=bool)
        else:
            v = _to_numpy(valid, "valid")
            if v.shape != p.shape[:2] or v.dtype != np.bool_:
                raise ValueError(f"valid: expected bool {p.shape[:2]}, got {v.dtype} {v.shape}")
        self.skipped_frames += int((~v).sum())
        for s in range(self.steps):
            keep = v[:, s]
            if not keep.any():
                continue
            self.per_step[s].update(p[keep, s], g[keep, s], None if m is None else m[keep, s])

    def merge(self, other: ForecastMetric) -> ForecastMetric:
        """Add another accumulator's counts; returns self."""
        if not isinstance(other, ForecastMetric) or other.steps != self.steps:
            raise ValueError("other: expected a ForecastMetric with the same steps")
        for a, b in zip(self.per_step, other.per_step):
            a.merge(b)
        self.skipped_frames += other.skipped_frames
        return self

    def compute(self) -> dict:
        """Forecast metrics.

        Returns:
            dict with ``miou@1s``, ``miou@2s``, ``miou@3s``, ``miou_avg``, ``iou@1s`` ...
            ``iou_avg`` (geometry IoU), ``movers_miou@1s`` ... ``movers_miou_avg``
            (:func:`movers_miou`), ``miou_per_step`` / ``iou_per_step`` /
            ``movers_miou_per_step`` lists (S),
            ``skipped_frames``, ``region``, ``protocol``.
        """
        res = [m.compute() for m in self.per_step]
        for r, m in zip(res, self.per_step):
            r["movers_miou"] = movers_miou(m.confusion)
        out: dict = {}
        names = (("miou", "miou"), ("iou_geometry", "iou"), ("movers_miou", "movers_miou"))
        for key, name in names:
            vals = [res[k - 1][key] for k in self.horizon_steps]
            for h, val in zip(self.horizons_s, vals):
                out[f"{name}@{h:g}s"] = val
            out[f"{name}_avg"] = float(np.mean(vals))
            out[f"{name}_per_step"] = [r[key] for r in res]
        out["skipped_frames"] = self.skipped_frames
        out["region"] = self.per_step[0].region
        at = ", ".join(f"{h:g}s=step {k}" for h, k in zip(self.horizons_s, self.horizon_steps))
        out["protocol"] = f"forecast at {at}; avg = mean of those horizons; {OCCUPANCY_PROTOCOL}"
        return out

    def format_table(self, label: str = "model") -> str:
        """Printable table (percent) whose header states protocol and region."""
        r = self.compute()
        hs = [f"{h:g}s" for h in self.horizons_s]
        head = "".join(f"{'mIoU@' + h:>11}" for h in hs) + f"{'mIoU avg':>10}"
        head += "".join(f"{'IoU@' + h:>10}" for h in hs) + f"{'IoU avg':>9}"
        row = (
            "".join(f"{100 * r['miou@' + h]:>11.2f}" for h in hs) + f"{100 * r['miou_avg']:>10.2f}"
        )
        row += "".join(f"{100 * r['iou@' + h]:>10.2f}" for h in hs) + f"{100 * r['iou_avg']:>9.2f}"
        return "\n".join(
            [f"# Forecast ({r['region']}): {r['protocol']}", f"{'':<16}{head}", f"{label:<16}{row}"]
        )
