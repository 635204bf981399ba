"""Output heads: the plain 18-way softmax and the factorised air-mask head (Eqs. 6.11-6.13).

The air-mask head splits each voxel's prediction into an air branch and a non-air branch:

    p(free)            = sigmoid(a)                      (air branch, one logit a per voxel)
    p(c), c non-air    = (1 - sigmoid(a)) * softmax(n)_c (non-air branch, 17 logits n)

These are proper probabilities over the 18 Occ3D classes, so the 18-way log-probabilities
``log p`` serve as the model's logits (CE, Lovász and any caller's softmax/argmax use them).
The paper's decision rule (Eq. 6.13, mask = "air predicted") reads the occupancy as free
where ``p(free) >= 0.5`` and otherwise as the most likely non-air class; that is what
:func:`scores_to_occupancy` does for air-mask heads. Softmax heads use the argmax.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES

__all__ = ["NON_AIR_IDS", "combine_air_mask", "scores_to_occupancy"]

#: Occ3D ids of the non-air classes, in the order of the non-air branch's outputs.
NON_AIR_IDS: tuple[int, ...] = tuple(c for c in range(NUM_OCC3D_CLASSES) if c != FREE_ID)

# Position of each Occ3D class in cat([non_air_log_probs, free_log_prob]).
_CAT_ORDER = list(NON_AIR_IDS) + [FREE_ID]
_INV_ORDER = tuple(_CAT_ORDER.index(c) for c in range(NUM_OCC3D_CLASSES))
# With Occ3D's ids free is the last class: no re-ordering and the non-air ids are a prefix.
_IDENTITY_ORDER = _INV_ORDER == tuple(range(NUM_OCC3D_CLASSES))


def combine_air_mask(air_logit: torch.Tensor, non_air_logits: torch.Tensor) -> torch.Tensor:
    """18-way log-probabilities of the factorised air-mask head.

    Args:
        air_logit: [..., ] logit of "voxel is free" (air branch).
        non_air_logits: [..., 17] logits over the non-air classes in ``NON_AIR_IDS`` order.

    Returns:
        [..., 18] log p over Occ3D classes (logsumexp over the last axis is 0).
    """
    if non_air_logits.shape[:-1] != air_logit.shape or non_air_logits.shape[-1] != len(NON_AIR_IDS):
        raise ValueError(
            f"non_air_logits: expected shape {tuple(air_logit.shape) + (len(NON_AIR_IDS),)}, "
            f"got {tuple(non_air_logits.shape)}"
        )
    log_free = F.logsigmoid(air_logit)
    log_occupied = F.logsigmoid(-air_logit)  # log(1 - sigmoid(a)), stable for large |a|
    log_classes = log_occupied[..., None] + F.log_softmax(non_air_logits, dim=-1)
    cat = torch.cat([log_classes, log_free[..., None]], dim=-1)
    if _IDENTITY_ORDER:
        return cat
    return cat.index_select(-1, torch.tensor(_INV_ORDER, device=cat.device))


def scores_to_occupancy(scores: torch.Tensor, air_mask_head: bool) -> torch.Tensor:
    """Per-voxel class decision.

    Args:
        scores: [..., 18] logits (softmax head) or log-probabilities (air-mask head).
        air_mask_head: Use Eq. 6.13's rule (free iff p(free) >= 0.5, else the best non-air
            class) instead of the argmax.

    Returns:
        [...] uint8 Occ3D class ids.
    """
    if scores.shape[-1] != NUM_OCC3D_CLASSES:
        raise ValueError(
            f"scores: expected last axis {NUM_OCC3D_CLASSES}, got {tuple(scores.shape)}"
        )
    if not air_mask_head:
        return scores.argmax(-1).to(torch.uint8)
    if _IDENTITY_ORDER:
        best = scores[..., : len(NON_AIR_IDS)].argmax(-1)
    else:
        non_air = torch.tensor(NON_AIR_IDS, device=scores.device)
        best = non_air[scores.index_select(-1, non_air).argmax(-1)]
    free = scores[..., FREE_ID] >= math.log(0.5)
    return torch.where(free, torch.full_like(best, FREE_ID), best).to(torch.uint8)
