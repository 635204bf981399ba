"""Reconstruction losses of the tokenizers: cross-entropy (optionally class-weighted) and
Lovász-softmax, for both output heads.

Softmax head: ``ce_weight * CE(logits, o) + lovasz_weight * Lovasz(softmax(logits), o)``.

Air-mask head (Eqs. 6.12, 6.14 with modified targets): the air branch is scored on every voxel
with a binary cross-entropy against ``o'_air = [o is free]``; the non-air branch is scored with
a 17-way cross-entropy on the non-air voxels only (its target is undefined on air voxels, where
the air mask decides the output). The two are averaged over their own voxels and summed; on an
all-free volume the non-air term is 0. Lovász-softmax is applied to the combined 18-way
probabilities of :func:`renderworld.tokenizer.heads.combine_air_mask`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer.heads import NON_AIR_IDS
from renderworld.tokenizer.lovasz import lovasz_softmax

__all__ = ["softmax_head_loss", "air_mask_head_loss", "weighted_mean"]


def weighted_mean(values: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """``sum(w * v) / sum(w)`` (plain mean when ``weights`` is None; 0 on empty input)."""
    if values.numel() == 0:
        return values.sum() * 0.0
    if weights is None:
        return values.mean()
    return (weights * values).sum() / weights.sum().clamp_min(1e-12)


def _lovasz(log_probs_or_logits, target, present_only, is_log_probs):
    flat = log_probs_or_logits.reshape(-1, NUM_OCC3D_CLASSES).float()
    probs = flat.exp() if is_log_probs else flat.softmax(-1)
    return lovasz_softmax(probs, target.reshape(-1), present_only=present_only)


def softmax_head_loss(
    logits: torch.Tensor,
    target: torch.Tensor,
    class_weights: torch.Tensor | None = None,
    ce_weight: float = 1.0,
    lovasz_weight: float = 1.0,
    present_only: bool = True,
) -> dict[str, torch.Tensor]:
    """Loss of an 18-way softmax head.

    Args:
        logits: [B, X, Y, Z, 18] class logits.
        target: [B, X, Y, Z] int64 Occ3D ids.
        class_weights: Optional [18] CE weights.
        ce_weight, lovasz_weight: Term weights.
        present_only: Lovász over classes present in the target only.

    Returns:
        ``{"recon": weighted sum, "ce": CE, "lovasz": Lovasz}`` scalars.
    """
    flat = logits.reshape(-1, NUM_OCC3D_CLASSES).float()
    tgt = target.reshape(-1)
    ce = F.cross_entropy(flat, tgt, weight=class_weights)
    lov = _lovasz(flat, tgt, present_only, is_log_probs=False)
    return {"recon": ce_weight * ce + lovasz_weight * lov, "ce": ce, "lovasz": lov}


def air_mask_head_loss(
    air_logit: torch.Tensor,
    non_air_logits: torch.Tensor,
    log_probs: torch.Tensor,
    target: torch.Tensor,
    class_weights: torch.Tensor | None = None,
    ce_weight: float = 1.0,
    lovasz_weight: float = 1.0,
    present_only: bool = True,
) -> dict[str, torch.Tensor]:
    """Loss of the factorised air-mask head.

    Args:
        air_logit: [B, X, Y, Z] logit of "free".
        non_air_logits: [B, X, Y, Z, 17] non-air class logits (``NON_AIR_IDS`` order).
        log_probs: [B, X, Y, Z, 18] combined log-probabilities (for Lovász).
        target: [B, X, Y, Z] int64 Occ3D ids.
        class_weights: Optional [18] weights; a voxel's BCE and CE are weighted by the weight
            of its true class.
        ce_weight, lovasz_weight, present_only: As in :func:`softmax_head_loss`.

    Returns:
        ``{"recon", "ce" (= air + non_air), "air", "non_air", "lovasz"}`` scalars.
    """
    tgt = target.reshape(-1)
    w = class_weights[tgt] if class_weights is not None else None
    is_free = (tgt == FREE_ID).float()
    bce = F.binary_cross_entropy_with_logits(
        air_logit.reshape(-1).float(), is_free, reduction="none"
    )
    air = weighted_mean(bce, w)
    occupied = tgt != FREE_ID
    lut = torch.full((NUM_OCC3D_CLASSES,), -1, dtype=torch.int64, device=tgt.device)
    lut[torch.tensor(NON_AIR_IDS, device=tgt.device)] = torch.arange(
        len(NON_AIR_IDS), device=tgt.device
    )
    na_logits = non_air_logits.reshape(-1, len(NON_AIR_IDS))[occupied].float()
    if na_logits.shape[0] == 0:  # all-free: keep a (zero) gradient path to the branch
        non_air = non_air_logits.sum() * 0.0
    else:
        ce_na = F.cross_entropy(na_logits, lut[tgt[occupied]], reduction="none")
        non_air = weighted_mean(ce_na, w[occupied] if w is not None else None)
    ce = air + non_air
    lov = _lovasz(log_probs, tgt, present_only, is_log_probs=True)
    return {
        "recon": ce_weight * ce + lovasz_weight * lov,
        "ce": ce,
        "air": air,
        "non_air": non_air,
        "lovasz": lov,
    }
