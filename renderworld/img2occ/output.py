"""What ``Img2Occ.forward`` returns, and the per-view gather it uses."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from renderworld.img2occ.head import AnchorGaussians
from renderworld.img2occ.render import RenderedViews

__all__ = ["Img2OccOutput"]


@dataclass
class Img2OccOutput:
    """What ``Img2Occ.forward`` returns.

    Attributes:
        gaussians: one Gaussian per voxel, [B, V, ...] (V = X·Y·Z, row-major [x, y, z]).
        visibility: [B, X, Y, Z] number of cameras that see each voxel centre.
        grid_shape: (X, Y, Z).
        views: renders of the keyframe cameras ``view_index`` (None when not rendered).
        view_index: [B, Cr] int64 camera indices rendered per sample (None when not rendered).
        adj_views: renders of the adjacent-frame cameras ``adj_index`` (or None).
        adj_index: [B, Ca] int64 (or None).
        image_logits: depth-aware lifting only: [B, C, D + K, h, w] per-pixel depth-bin and
            class logits of the keyframe cameras (else None).
        fine_logits: ``fine_semantics`` only: [B, C, K, h_f, w_f] class logits at the
            encoder's first stage (else None).
    """

    gaussians: AnchorGaussians
    visibility: torch.Tensor
    grid_shape: tuple[int, int, int]
    views: RenderedViews | None = None
    view_index: torch.Tensor | None = None
    adj_views: RenderedViews | None = None
    adj_index: torch.Tensor | None = None
    image_logits: torch.Tensor | None = None
    fine_logits: torch.Tensor | None = None


def _gather_views(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """x [B, C, ...] → [B, Cr, ...] along dim 1."""
    idx = index.to(x.device).view(*index.shape, *([1] * (x.ndim - 2)))
    return torch.gather(x, 1, idx.expand(*index.shape, *x.shape[2:]))
