"""A fine per-pixel semantic head (an option, not in the paper).

The depth-aware lifting's class logits live on the stride-8 feature map, where a pedestrian
or a traffic cone 20 m away covers less than a pixel and is averaged away. This head predicts
class logits at the encoder's first stage (stride 2), from those features and the upsampled
stride-8 context, supervised by the LiDAR-projected 2-D semantic maps with a class-balanced
cross-entropy; its probabilities replace the coarse ones in the lifting, and the lifted class
distribution is added to the Gaussians' logits through a learned skip (``Img2Occ``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES
from renderworld.img2occ.depth_lift import _masked_mean, sample_at_labels
from renderworld.img2occ.encoder import _norm
from renderworld.img2occ.losses import balanced_class_weights
from renderworld.precision import float32_boundary

__all__ = ["FineSemanticHead", "pixel_class_loss"]


class FineSemanticHead(nn.Module):
    """Class logits at the fine (stride-2) resolution.

    Args:
        fine_channels: channels of the fine map.
        context_channels: channels of the coarse feature map (upsampled to the fine size).
        hidden: hidden channels.

    ``forward(fine [N, Cf, h, w], context [N, Cc, h', w'])`` → [N, K, h, w], K = 17.
    """

    def __init__(self, fine_channels: int, context_channels: int, hidden: int = 32):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(fine_channels + context_channels, hidden, 3, padding=1, bias=False),
            _norm(hidden),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, hidden, 1, bias=False),
            _norm(hidden),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, NUM_SEMANTIC_CLASSES, 1),
        )

    def forward(self, fine: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        up = F.interpolate(context, size=fine.shape[-2:], mode="bilinear", align_corners=False)
        return self.net(torch.cat([fine, up], dim=1))


@float32_boundary  # float32: label-pixel projection and a cross-entropy
def pixel_class_loss(
    logits: torch.Tensor,
    k_map: torch.Tensor,
    k_label: torch.Tensor,
    semantics: torch.Tensor,
    balance: float = 0.0,
) -> torch.Tensor:
    """Cross-entropy of per-pixel class logits against the 2-D LiDAR semantic maps.

    The logits are sampled bilinearly at every label pixel's centre; pixels labelled 255
    or ``FREE_ID`` do not count.

    Args:
        logits: [B, C, K, h, w] class logits.
        k_map: [B, C, 3, 3] intrinsics of the logit maps.
        k_label: [B, C, 3, 3] intrinsics of the label maps.
        semantics: [B, C, H_r, W_r] int64 ids 0..16 (255 = no label).
        balance: p in [0, 1]: weigh each label by its frequency among the batch's labelled
            pixels to the power -p (weights normalised to mean 1 over those pixels).

    Returns:
        Scalar; 0 with a graph when no pixel is labelled.
    """
    b, c, k = logits.shape[:3]
    if k != NUM_SEMANTIC_CLASSES or semantics.shape[:2] != (b, c) or semantics.ndim != 4:
        raise ValueError(
            f"logits/semantics: expected [{b}, {c}, {NUM_SEMANTIC_CLASSES}, h, w] and "
            f"[{b}, {c}, H_r, W_r], got {tuple(logits.shape)} and {tuple(semantics.shape)}"
        )
    if not (0.0 <= float(balance) <= 1.0):
        raise ValueError(f"balance: expected a value in [0, 1], got {balance!r}")
    s = sample_at_labels(logits, k_map, k_label, semantics.shape[-2:]).reshape(-1, k)
    sem = semantics.flatten(0, 1).to(s.device).long().reshape(-1)
    target = torch.where((sem >= 0) & (sem < FREE_ID), sem, torch.full_like(sem, -1))
    ce = F.cross_entropy(s, target, reduction="none", ignore_index=-1)
    valid = target >= 0
    weights = None
    if balance > 0:
        per_class = balanced_class_weights(target[valid], balance).to(s.dtype)
        weights = per_class[target.clamp_min(0)]
    return _masked_mean(ce, valid, weights)
