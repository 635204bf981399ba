"""Heading error of planned poses: median and mean at each horizon, in degrees.

The error of a future frame is the absolute wrapped difference between the planned and the
ground-truth ego heading (yaw, current ego frame), in degrees [0, 180]. Frames past the end of
a scene are left out. Accumulation is by counts that add over shards: per step a histogram of
the errors (:data:`HEADING_EDGES_DEG`: bins of :data:`HEADING_BIN_DEG` degrees up to
:data:`HEADING_FINE_MAX_DEG`, of 0.1 degree above), the sum of the errors and their number.
The mean is exact; the median takes the centre of its bin (of each of the two middle ranks'
bins for an even count), so below ``HEADING_FINE_MAX_DEG`` it is exact to half of
``HEADING_BIN_DEG``.
"""

from __future__ import annotations

import numpy as np

from renderworld.metrics.occupancy import _to_numpy

__all__ = [
    "HEADING_BIN_DEG",
    "HEADING_BINS",
    "HEADING_EDGES_DEG",
    "HEADING_FINE_MAX_DEG",
    "heading_error_deg",
    "heading_counts",
    "heading_from_counts",
]

#: Width of a histogram bin below ``HEADING_FINE_MAX_DEG``, degrees (the median's resolution).
HEADING_BIN_DEG = 0.001
#: Errors up to this many degrees fall in the fine bins; above it bins are 0.1 degree wide.
HEADING_FINE_MAX_DEG = 20.0
#: Bin edges, degrees, from 0 to 180 (the last bin also holds 180).
HEADING_EDGES_DEG = np.concatenate(
    [
        np.arange(round(HEADING_FINE_MAX_DEG / HEADING_BIN_DEG)) * HEADING_BIN_DEG,
        HEADING_FINE_MAX_DEG + np.arange(round((180.0 - HEADING_FINE_MAX_DEG) / 0.1) + 1) * 0.1,
    ]
)
#: Number of histogram bins.
HEADING_BINS = len(HEADING_EDGES_DEG) - 1


def heading_error_deg(pred_yaw, gt_yaw) -> np.ndarray:
    """Absolute wrapped heading difference in degrees [0, 180].

    Args:
        pred_yaw: [...] radians.
        gt_yaw: same shape, radians.

    Returns:
        float64 array of the input shape.
    """
    p = _to_numpy(pred_yaw, "pred_yaw").astype(np.float64)
    g = _to_numpy(gt_yaw, "gt_yaw").astype(np.float64)
    if p.shape != g.shape:
        raise ValueError(f"gt_yaw: expected shape {p.shape}, got {g.shape}")
    d = p - g
    return np.abs(np.degrees(np.arctan2(np.sin(d), np.cos(d))))


def heading_counts(pred_yaw, gt_yaw, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-step counts of a batch of planned headings.

    Args:
        pred_yaw: [B, S] radians, current ego frame.
        gt_yaw: [B, S] radians.
        valid: [B, S] bool, False for frames past the scene end.

    Returns:
        (histogram [S, HEADING_BINS] float64, error sum [S] degrees, count [S]) of the valid
        frames.
    """
    err = heading_error_deg(pred_yaw, gt_yaw)
    v = _to_numpy(valid, "valid").astype(bool)
    if err.ndim != 2 or v.shape != err.shape:
        raise ValueError(f"valid: expected bool [B, S] like the yaws {err.shape}, got {v.shape}")
    idx = np.clip(np.searchsorted(HEADING_EDGES_DEG, err, side="right") - 1, 0, HEADING_BINS - 1)
    steps = err.shape[1]
    hist = np.zeros((steps, HEADING_BINS))
    for s in range(steps):
        np.add.at(hist[s], idx[v[:, s], s], 1.0)
    return hist, np.where(v, err, 0.0).sum(0), v.sum(0).astype(np.float64)


def heading_from_counts(hist, err_sum, count, horizon_steps) -> dict[str, list[float]]:
    """Median and mean heading error (degrees) at each horizon step.

    Args:
        hist: [S, HEADING_BINS] summed histograms (:func:`heading_counts`).
        err_sum: [S] summed errors, degrees.
        count: [S] summed counts.
        horizon_steps: 1-based steps to report.

    Returns:
        ``{"median": [...], "mean": [...]}`` per horizon step, NaN where no frame counted.
    """
    h = np.asarray(hist, dtype=np.float64)
    s, n = np.asarray(err_sum, dtype=np.float64), np.asarray(count, dtype=np.float64)
    med, mean = [], []
    for k in horizon_steps:
        row, total = h[k - 1], n[k - 1]
        if total <= 0:
            med.append(float("nan"))
            mean.append(float("nan"))
            continue
        cum = np.cumsum(row)
        # The median's two middle ranks (the same one for an odd count), each at its bin centre.
        ranks = (np.floor((total + 1) / 2), np.ceil((total + 1) / 2))
        bins = [int(np.searchsorted(cum, r - 0.5)) for r in ranks]
        centres = [(HEADING_EDGES_DEG[b] + HEADING_EDGES_DEG[b + 1]) / 2 for b in bins]
        med.append(float(np.mean(centres)))
        mean.append(float(s[k - 1] / total))
    return {"median": med, "mean": mean}
