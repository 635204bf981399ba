"""Depth-aware lifting pieces: per-pixel depth / class predictions and their 2-D losses.

With ``Img2OccConfig.depth_bins = D > 0`` the image branch predicts, per feature pixel, a
categorical distribution over D equal-width camera-z bins spanning ``depth_range`` and logits
over the K = 17 semantic classes (LSS-style). Both are supervised directly by the
LiDAR-projected 2-D depth and semantic maps the batch already carries, so the model is still
trained from 2-D labels only. The lifting (``lift_features``) weighs a camera's feature at a
voxel by the predicted probability mass of the camera's surface inside the voxel's depth
interval ``[z - r, z + r]``: ``CDF(z + r) - CDF(z - r)``, with the CDF piecewise linear in z
(uniform density inside each bin), so the weight is differentiable in the predictions.

This module also holds the voxel losses of the "3d" upper-reference supervision.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES
from renderworld.img2occ.encoder import _norm
from renderworld.precision import float32_boundary

__all__ = [
    "DepthSemanticHead",
    "depth_bin_edges",
    "depth_bin_targets",
    "depth_cdf",
    "interp_cdf",
    "image_label_losses",
    "sample_at_labels",
    "occupancy_3d_loss",
]


def depth_bin_edges(num_bins: int, depth_range: tuple[float, float]) -> torch.Tensor:
    """[D + 1] equal-width bin edges (metres, camera z) over ``depth_range``."""
    if isinstance(num_bins, bool) or not isinstance(num_bins, int) or num_bins < 2:
        raise ValueError(f"num_bins: expected an int >= 2, got {num_bins!r}")
    lo, hi = (float(v) for v in depth_range)
    if not 0 < lo < hi:
        raise ValueError(f"depth_range: expected 0 < d_min < d_max, got {depth_range!r}")
    return torch.linspace(lo, hi, num_bins + 1, dtype=torch.float64)


class DepthSemanticHead(nn.Module):
    """Per-pixel depth-bin logits and class logits from image features.

    Args:
        channels: input feature channels.
        num_bins: D depth bins.

    Input [N, channels, h, w]; output [N, D + K, h, w] (depth logits first, K = 17).
    """

    def __init__(self, channels: int, num_bins: int):
        super().__init__()
        self.num_bins = num_bins
        self.net = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1, bias=False),
            _norm(channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(channels, num_bins + NUM_SEMANTIC_CLASSES, 1),
        )

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features)


@float32_boundary  # float32: a cumulative sum over depth bins
def depth_cdf(depth_logits: torch.Tensor) -> torch.Tensor:
    """CDF at the bin edges of the softmax over dim 1: [N, D, ...] → [N, D + 1, ...].

    Entry 0 is 0 and entry D is 1 (up to rounding), non-decreasing in between.
    """
    p = torch.softmax(depth_logits, dim=1)
    zero = torch.zeros_like(p[:, :1])
    return torch.cat([zero, p.cumsum(1)], dim=1).clamp(0.0, 1.0)


def interp_cdf(cdf: torch.Tensor, edges: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Evaluate a piecewise-linear CDF given at equal-width bin edges.

    Args:
        cdf: [B, D + 1, V] CDF values at ``edges`` (one CDF per voxel).
        edges: [D + 1] equal-width edges, metres.
        z: [B, V] depths, metres; below edges[0] gives cdf[:, 0], above edges[-1] cdf[:, -1].

    Returns:
        [B, V], differentiable in ``cdf`` (not in ``z``: the bin index is detached).
    """
    d = edges.numel() - 1
    if cdf.ndim != 3 or cdf.shape[1] != d + 1 or z.shape != (cdf.shape[0], cdf.shape[2]):
        raise ValueError(
            f"cdf/z: expected [B, {d + 1}, V] and [B, V], got {tuple(cdf.shape)} and "
            f"{tuple(z.shape)}"
        )
    lo = float(edges[0])
    step = float(edges[-1] - edges[0]) / d
    pos = ((z.detach() - lo) / step).clamp(0.0, float(d))
    i0 = pos.floor().clamp(max=d - 1).long()
    frac = (pos - i0.to(pos.dtype)).to(cdf.dtype)
    c0 = cdf.gather(1, i0[:, None])[:, 0]
    c1 = cdf.gather(1, (i0 + 1)[:, None])[:, 0]
    return c0 + (c1 - c0) * frac


def depth_bin_targets(depth: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Bin index of each LiDAR depth; -1 where there is no point or it is out of range.

    Args:
        depth: [...] metres camera z (0 = no point).
        edges: [D + 1] equal-width edges.

    Returns:
        [...] int64 in 0..D-1 or -1.
    """
    d = edges.numel() - 1
    lo, hi = float(edges[0]), float(edges[-1])
    idx = ((depth - lo) / ((hi - lo) / d)).floor().long().clamp(0, d - 1)
    ok = (depth >= lo) & (depth < hi)
    return torch.where(ok, idx, torch.full_like(idx, -1))


def _label_grid(k_feat: torch.Tensor, k_label: torch.Tensor, hw_label, hw_feat) -> torch.Tensor:
    """grid_sample coordinates [N, H_r, W_r, 2] of the label pixels' centres in feature maps.

    Both intrinsics describe the same camera (zero skew), so a label pixel centre (u, v)
    maps to the feature coordinates ``K_feat K_label^-1 [u, v, 1]``.
    """
    h_r, w_r = hw_label
    h_f, w_f = hw_feat
    dt = k_feat.dtype
    v, u = torch.meshgrid(
        torch.arange(h_r, dtype=dt, device=k_feat.device) + 0.5,
        torch.arange(w_r, dtype=dt, device=k_feat.device) + 0.5,
        indexing="ij",
    )
    sx = k_feat[:, 0, 0] / k_label[:, 0, 0]
    sy = k_feat[:, 1, 1] / k_label[:, 1, 1]
    x = (u[None] - k_label[:, 0, 2, None, None]) * sx[:, None, None] + k_feat[:, 0, 2, None, None]
    y = (v[None] - k_label[:, 1, 2, None, None]) * sy[:, None, None] + k_feat[:, 1, 2, None, None]
    return torch.stack([2.0 * x / w_f - 1.0, 2.0 * y / h_f - 1.0], dim=-1)


def sample_at_labels(
    maps: torch.Tensor, k_map: torch.Tensor, k_label: torch.Tensor, label_hw
) -> torch.Tensor:
    """Bilinear samples of per-camera maps at every label pixel's centre.

    Args:
        maps: [B, C, F, h, w] per-camera maps (e.g. logits).
        k_map: [B, C, 3, 3] intrinsics of the maps.
        k_label: [B, C, 3, 3] intrinsics of the label maps.
        label_hw: (H_r, W_r) of the label maps.

    Returns:
        [B·C, H_r, W_r, F].
    """
    flat = maps.flatten(0, 1)
    grid = _label_grid(
        k_map.flatten(0, 1).to(flat.dtype),
        k_label.flatten(0, 1).to(flat.dtype),
        label_hw,
        flat.shape[-2:],
    )
    s = F.grid_sample(flat, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return s.permute(0, 2, 3, 1)


@float32_boundary  # float32: label-pixel projection and cross-entropies
def image_label_losses(
    logits: torch.Tensor,
    k_feat: torch.Tensor,
    k_label: torch.Tensor,
    depth: torch.Tensor,
    semantics: torch.Tensor,
    edges: torch.Tensor,
    class_weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross-entropies of the per-pixel depth bins and classes against 2-D LiDAR labels.

    The predictions are sampled bilinearly at every label pixel's centre. Pixels without a
    LiDAR point, out of the bins' range or with label 255 / ``FREE_ID`` do not count.

    Args:
        logits: [B, C, D + K, h, w] the :class:`DepthSemanticHead` output.
        k_feat: [B, C, 3, 3] intrinsics at the feature-map resolution.
        k_label: [B, C, 3, 3] intrinsics of the label maps.
        depth: [B, C, H_r, W_r] metres camera z (0 = no point).
        semantics: [B, C, H_r, W_r] int64 ids 0..16 (255 = no label).
        edges: [D + 1] depth-bin edges.
        class_weights: optional [>= K] weight per class id of the semantic CE (weighted mean).

    Returns:
        ``(depth_ce, semantic_ce)`` scalars; each 0 with a graph when no pixel counts.
    """
    d = edges.numel() - 1
    if logits.ndim != 5 or logits.shape[2] != d + NUM_SEMANTIC_CLASSES:
        raise ValueError(
            f"logits: expected [B, C, {d + NUM_SEMANTIC_CLASSES}, h, w], got {tuple(logits.shape)}"
        )
    b, c = logits.shape[:2]
    if depth.shape[:2] != (b, c) or semantics.shape != depth.shape:
        raise ValueError(
            f"depth/semantics: expected equal [{b}, {c}, H_r, W_r] shapes, got "
            f"{tuple(depth.shape)} and {tuple(semantics.shape)}"
        )
    s = sample_at_labels(logits, k_feat, k_label, depth.shape[-2:])  # [N, H_r, W_r, D + K]
    dt = depth.flatten(0, 1).to(device=s.device)
    target_d = depth_bin_targets(dt, edges.to(dt.device))
    sem = semantics.flatten(0, 1).to(s.device).long()
    target_s = torch.where((sem >= 0) & (sem < FREE_ID), sem, torch.full_like(sem, -1))
    ce_d = F.cross_entropy(
        s[..., :d].reshape(-1, d), target_d.reshape(-1), reduction="none", ignore_index=-1
    )
    ce_s = F.cross_entropy(
        s[..., d:].reshape(-1, NUM_SEMANTIC_CLASSES),
        target_s.reshape(-1),
        reduction="none",
        ignore_index=-1,
    )
    ts = target_s.reshape(-1)
    w = None
    if class_weights is not None:
        w = class_weights.to(ce_s)[:NUM_SEMANTIC_CLASSES][ts.clamp_min(0)]
    return _masked_mean(ce_d, target_d.reshape(-1) >= 0), _masked_mean(ce_s, ts >= 0, w)


def _masked_mean(x: torch.Tensor, m: torch.Tensor, w: torch.Tensor | None = None) -> torch.Tensor:
    x = torch.where(m, x, torch.zeros_like(x))
    if w is not None:
        w = torch.where(m, w, torch.zeros_like(w))
        return (x * w).sum() / w.sum().clamp_min(1e-6)
    return x.sum() / m.sum().clamp_min(1).to(x.dtype)


@float32_boundary  # float32: BCE of opacities near 0 and 1
def occupancy_3d_loss(
    opacities: torch.Tensor,
    logits: torch.Tensor,
    occ: torch.Tensor,
    mask: torch.Tensor,
    eps: float = 1e-6,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel losses against Occ3D GT (the "3d" upper reference), inside ``mask``.

    Args:
        opacities: [B, V] in (0, 1).
        logits: [B, V, K] class logits.
        occ: [B, X, Y, Z] uint8/int64 Occ3D ids 0..17 (``FREE_ID`` = free), X·Y·Z = V.
        mask: [B, X, Y, Z] bool voxels that count (the camera mask).
        eps: clamp of the opacities inside the logs.
        weights: optional [B, X, Y, Z] per-voxel weights (> 0) of both means.

    Returns:
        ``(bce, ce)``: binary cross-entropy of the opacity against occupied (id < FREE_ID)
        over masked voxels, and the class cross-entropy over masked occupied voxels; each
        0 with a graph when nothing counts.
    """
    b, v = opacities.shape
    if logits.shape != (b, v, NUM_SEMANTIC_CLASSES):
        raise ValueError(
            f"logits: expected {(b, v, NUM_SEMANTIC_CLASSES)}, got {tuple(logits.shape)}"
        )
    if occ.shape[0] != b or occ[0].numel() != v or mask.shape != occ.shape:
        raise ValueError(
            f"occ/mask: expected [{b}, X, Y, Z] with X·Y·Z = {v} and equal shapes, got "
            f"{tuple(occ.shape)} and {tuple(mask.shape)}"
        )
    target = occ.reshape(b, v).to(opacities.device).long()
    m = mask.reshape(b, v).to(opacities.device).bool()
    occupied = target < FREE_ID
    o = opacities.clamp(eps, 1.0 - eps)
    bce = -torch.where(occupied, torch.log(o), torch.log1p(-o))
    ce = F.cross_entropy(
        logits.reshape(-1, NUM_SEMANTIC_CLASSES),
        torch.where(occupied, target, torch.zeros_like(target)).reshape(-1),
        reduction="none",
    )
    w = None if weights is None else weights.reshape(-1).to(bce)
    return _masked_mean(bce.reshape(-1), m.reshape(-1), w), _masked_mean(
        ce, (m & occupied).reshape(-1), w
    )
