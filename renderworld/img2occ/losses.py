"""Img2Occ losses on rendered views: semantic NLL and Pearson depth (paper Eq. 6.6, 6.7).

Both return a defined value with an autograd graph on degenerate inputs (no labelled pixels,
constant or single-pixel depth), so a training step never sees NaN (docs/conventions.md#numerics).
"""

from __future__ import annotations

import torch

from renderworld.constants import FREE_ID, IGNORE_LABEL, NUM_SEMANTIC_CLASSES
from renderworld.precision import float32_boundary

__all__ = [
    "IGNORE_LABEL",
    "semantic_nll_loss",
    "pearson_depth_loss",
    "relative_depth_l1_loss",
    "rendered_distribution",
    "balanced_class_weights",
]

# Per-pixel variance floor (m^2) in the correlation's denominator: bounds the gradient when
# the rendered depth is (nearly) constant; negligible next to real depth variances.
_VAR_FLOOR = 1e-6
# A target image whose depth standard deviation is below 0.1 mm is "constant".
_MIN_TARGET_VAR = 1e-8


def rendered_distribution(features: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Per-pixel distribution over the K classes plus "ray escaped".

    The rasterizer blends the Gaussians' class probabilities with weights summing to the
    accumulated alpha, so ``features`` sums to ``alpha`` and the remaining ``1 - alpha`` is
    the probability that the ray met nothing. Index K of the result equals ``FREE_ID``.

    Args:
        features: [..., K] rendered class probabilities (blended softmax), K = 17.
        alpha: [...] accumulated opacity.

    Returns:
        [..., K + 1] non-negative, summing to 1 (renormalised against rasterizer clamping).
    """
    escaped = (1.0 - alpha).clamp_min(0.0)[..., None]
    dist = torch.cat([features.clamp_min(0.0), escaped], dim=-1)
    return dist / dist.sum(-1, keepdim=True).clamp_min(1e-12)


def balanced_class_weights(labels: torch.Tensor, power: float) -> torch.Tensor:
    """Per-label weights ``frequency ** -power`` from the labels of one batch.

    Frequencies count the labelled pixels (ids 0..``FREE_ID``; 255 ignored); the weights are
    scaled so that their mean over those pixels is 1 (the loss scale is unchanged), and
    absent labels get weight 1.

    Args:
        labels: [...] int64 ids 0..``FREE_ID`` or 255.
        power: 0 gives all ones; 0.5 is inverse square-root frequency.

    Returns:
        [FREE_ID + 1] float32 weights.
    """
    if not (0.0 <= float(power) <= 1.0):
        raise ValueError(f"power: expected a value in [0, 1], got {power!r}")
    lab = labels.reshape(-1).long()
    lab = lab[(lab >= 0) & (lab <= FREE_ID)]
    counts = torch.bincount(lab, minlength=FREE_ID + 1).to(torch.float32)
    total = counts.sum()
    if power == 0 or total == 0:
        return torch.ones(FREE_ID + 1, device=labels.device)
    w = torch.where(counts > 0, (counts / total).clamp_min(1e-12) ** -float(power), 0.0)
    w = w / ((w * counts).sum() / total)
    return torch.where(counts > 0, w, torch.ones_like(w))


@float32_boundary  # float32: log of blended probabilities near prob_eps
def semantic_nll_loss(
    features: torch.Tensor,
    alpha: torch.Tensor,
    labels: torch.Tensor,
    eps: float = 1e-6,
    class_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Cross-entropy of rendered semantics against LiDAR-projected labels.

    Pixels with low accumulated alpha still count: their probability mass sits on "ray
    escaped", so the loss is high and its gradient raises the opacity of the Gaussians along
    the ray, i.e. it pushes occupancy where LiDAR saw a surface.

    Args:
        features: [N, H, W, K] rendered class probabilities.
        alpha: [N, H, W] accumulated alpha.
        labels: [N, H, W] int64 Occ3D ids 0..16, ``FREE_ID`` (ray escaped) or 255 (no label).
        eps: added inside the log.
        class_weights: optional [FREE_ID + 1] weight per label (e.g.
            :func:`balanced_class_weights`); the mean is then weighted.

    Returns:
        Scalar mean NLL over labelled pixels; 0 (with a graph) when none is labelled.
    """
    if features.shape[-1] != NUM_SEMANTIC_CLASSES:
        raise ValueError(
            f"features: expected {NUM_SEMANTIC_CLASSES} class channels, got {features.shape[-1]}"
        )
    if alpha.shape != features.shape[:-1] or labels.shape != alpha.shape:
        raise ValueError(
            f"alpha/labels: expected shape {tuple(features.shape[:-1])}, got "
            f"{tuple(alpha.shape)} and {tuple(labels.shape)}"
        )
    labels = labels.long()
    valid = labels != IGNORE_LABEL
    bad = valid & ((labels < 0) | (labels > FREE_ID))
    if bool(bad.any()):
        raise ValueError(
            f"labels: expected ids 0..{FREE_ID} or {IGNORE_LABEL}, got "
            f"{sorted(set(labels[bad].unique().tolist()))[:5]}"
        )
    dist = rendered_distribution(features, alpha)
    target = torch.where(valid, labels, torch.zeros_like(labels))
    p = dist.gather(-1, target[..., None])[..., 0]
    nll = -torch.log(p + eps)
    m = valid.to(nll.dtype)
    if class_weights is not None:
        if class_weights.shape != (FREE_ID + 1,):
            raise ValueError(
                f"class_weights: expected [{FREE_ID + 1}], got {tuple(class_weights.shape)}"
            )
        m = m * class_weights.to(nll)[target]
        return (nll * m).sum() / m.sum().clamp_min(1e-6)
    return (nll * m).sum() / m.sum().clamp_min(1.0)


@float32_boundary  # float32: moments over every LiDAR pixel: bf16 sums cancel
def pearson_depth_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """``1 - corr(rendered, target)`` per image over pixels with LiDAR depth, averaged.

    Images with fewer than two valid pixels or a constant target depth carry no correlation
    and are left out of the average; with none left the loss is 0 with a graph.

    Args:
        rendered: [N, H, W] rendered expected depth, metres.
        target: [N, H, W] LiDAR depth, metres (0 = no point).
        mask: [N, H, W] bool pixels to use; default ``target > 0``.

    Returns:
        Scalar loss in [0, 2].
    """
    if rendered.shape != target.shape or rendered.ndim != 3:
        raise ValueError(
            f"rendered/target: expected equal [N, H, W] shapes, got {tuple(rendered.shape)} "
            f"and {tuple(target.shape)}"
        )
    if mask is None:
        mask = target > 0
    elif mask.shape != target.shape:
        raise ValueError(f"mask: expected shape {tuple(target.shape)}, got {tuple(mask.shape)}")
    m = mask.to(rendered.dtype)
    t = torch.where(mask, target.to(rendered.dtype), torch.zeros_like(rendered))
    n = m.sum((1, 2))
    n1 = n.clamp_min(1.0)
    xr = (rendered - ((rendered * m).sum((1, 2)) / n1)[:, None, None]) * m
    xt = (t - ((t * m).sum((1, 2)) / n1)[:, None, None]) * m
    cov = (xr * xt).sum((1, 2))
    var_r = (xr * xr).sum((1, 2))
    var_t = (xt * xt).sum((1, 2))
    floor = _VAR_FLOOR * n1
    corr = cov / torch.sqrt((var_r + floor) * (var_t + floor))
    ok = ((n >= 2) & (var_t > _MIN_TARGET_VAR * n1)).to(rendered.dtype)
    return ((1.0 - corr) * ok).sum() / ok.sum().clamp_min(1.0)


@float32_boundary  # float32: relative errors of ~1e-2 are below bf16's resolution
def relative_depth_l1_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean of ``|rendered - target| / target`` over pixels with LiDAR depth.

    Args:
        rendered: [N, H, W] rendered expected depth, metres.
        target: [N, H, W] LiDAR depth, metres (0 = no point).
        mask: [N, H, W] bool pixels to use; default ``target > 0``.

    Returns:
        Scalar; 0 with a graph when no pixel is valid.
    """
    if rendered.shape != target.shape:
        raise ValueError(
            f"rendered/target: expected equal shapes, got {tuple(rendered.shape)} and "
            f"{tuple(target.shape)}"
        )
    if mask is None:
        mask = target > 0
    mask = mask & (target > 0)
    t = torch.where(mask, target.to(rendered.dtype), torch.ones_like(rendered))
    err = (rendered - t).abs() / t
    m = mask.to(rendered.dtype)
    return (err * m).sum() / m.sum().clamp_min(1.0)
