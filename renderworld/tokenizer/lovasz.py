"""Lovász-softmax loss (Berman, Rannen Triki, Blaschko, CVPR 2018), written from its definition.

For class c, let ``g_i = [y_i = c]`` and the error ``m_i = |g_i - p_i(c)|`` in [0, 1]. The
Jaccard loss of a set M of mispredicted elements is

    Delta_c(M) = |M| / |{g = 1} U M|        (1 - IoU when M is the mispredicted set).

Its Lovász extension, evaluated at the error vector m, is

    Delta_bar_c(m) = sum_i m_(i) * (Delta_c({(1)..(i)}) - Delta_c({(1)..(i-1)})),

with ``m_(1) >= m_(2) >= ...`` sorted decreasingly. It is convex, piecewise linear, equals
Delta_c on 0/1 vectors (so it is the exact Jaccard loss of hard predictions) and equals the
integral ``int_0^1 Delta_c({i : m_i >= t}) dt``. The multi-class loss averages Delta_bar_c over
classes (all, or only those present in the target). An empty class with nothing predicted has
zero loss (Delta_c of the empty set is 0), so every case is defined and finite.
"""

from __future__ import annotations

import torch

__all__ = [
    "jaccard_increments",
    "lovasz_extension",
    "lovasz_softmax",
    "lovasz_softmax_reference",
]


def jaccard_increments(gt_sorted: torch.Tensor) -> torch.Tensor:
    """Increments of the Jaccard loss along a sorted order.

    Args:
        gt_sorted: [..., N] float 0/1 ground-truth membership, ordered (along the last axis)
            by decreasing error.

    Returns:
        [..., N] ``Delta({1..i}) - Delta({1..i-1})`` for the prefix sets of that order.
    """
    n_pos = gt_sorted.sum(-1, keepdim=True)
    # Prefix {1..i} counted as mispredicted: the true elements left correctly predicted and
    # the union of the true set with the prefix.
    intersection = n_pos - gt_sorted.cumsum(-1)
    union = n_pos + (1.0 - gt_sorted).cumsum(-1)  # >= 1 for every non-empty prefix
    jaccard = 1.0 - intersection / union
    return torch.cat([jaccard[..., :1], jaccard[..., 1:] - jaccard[..., :-1]], dim=-1)


def lovasz_extension(errors: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Lovász extension of the Jaccard loss of one class.

    Args:
        errors: [N] float errors ``|g_i - p_i|`` in [0, 1].
        gt: [N] 0/1 ground-truth membership.

    Returns:
        Scalar loss (0 for an empty input).
    """
    if errors.numel() == 0:
        return errors.sum()
    errors_sorted, perm = torch.sort(errors, descending=True)
    return torch.dot(errors_sorted, jaccard_increments(gt.to(errors.dtype)[perm]))


def _check(probs: torch.Tensor, target: torch.Tensor) -> None:
    if probs.dim() != 2:
        raise ValueError(f"probs: expected [N, K], got {tuple(probs.shape)}")
    if target.shape != probs.shape[:1]:
        raise ValueError(f"target: expected [{probs.shape[0]}], got {tuple(target.shape)}")


def lovasz_softmax(
    probs: torch.Tensor,
    target: torch.Tensor,
    present_only: bool = True,
    valid: torch.Tensor | None = None,
) -> torch.Tensor:
    """Multi-class Lovász-softmax loss (all classes sorted in one batched call).

    Args:
        probs: [N, K] class probabilities (rows sum to 1), any float dtype.
        target: [N] int64 class ids in [0, K).
        present_only: Average over classes present in ``target`` only (else over all K;
            an absent class then contributes the mass predicted for it).
        valid: Optional [N] bool mask of elements to score.

    Returns:
        Scalar loss in [0, 1]; 0 (with a gradient path) when no element is valid.

    Raises:
        ValueError: on mismatched shapes.
    """
    _check(probs, target)
    if valid is not None:
        probs, target = probs[valid], target[valid]
    if target.numel() == 0:
        return probs.sum() * 0.0
    k = probs.shape[1]
    fg = (target[None, :] == torch.arange(k, device=target.device)[:, None]).to(probs.dtype)
    errors = (fg - probs.t()).abs()  # [K, N]
    errors_sorted, perm = torch.sort(errors, dim=1, descending=True)
    per_class = (errors_sorted * jaccard_increments(torch.gather(fg, 1, perm))).sum(1)  # [K]
    if present_only:
        present = (fg.sum(1) > 0).to(per_class.dtype)  # never all 0: every element has a class
        return (per_class * present).sum() / present.sum()  # no boolean indexing: no host sync
    return per_class.mean()


def lovasz_softmax_reference(
    probs: torch.Tensor,
    target: torch.Tensor,
    present_only: bool = True,
    valid: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-class loop twin of :func:`lovasz_softmax` (test oracle); same arguments."""
    _check(probs, target)
    if valid is not None:
        probs, target = probs[valid], target[valid]
    if target.numel() == 0:
        return probs.sum() * 0.0
    losses = []
    for c in range(probs.shape[1]):
        fg = (target == c).to(probs.dtype)
        if present_only and not bool(fg.any()):
            continue
        losses.append(lovasz_extension((fg - probs[:, c]).abs(), fg))
    return torch.stack(losses).mean()
