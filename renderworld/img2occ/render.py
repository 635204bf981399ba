"""Render the anchor Gaussians' semantics and depth into cameras with the splat rasterizer.

The Gaussians live in the keyframe's ego frame, so a camera's view matrix (world→camera) is
the inverse of its ``cam_to_ego``. Gaussians whose opacity is at most ``prune_opacity`` are
not rendered ("skip air"); the selection is detached, the kept Gaussians' gradients are exact.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from renderworld.constants import NUM_SEMANTIC_CLASSES
from renderworld.geometry import invert_pose
from renderworld.img2occ.head import AnchorGaussians

__all__ = ["RenderedViews", "render_views", "default_render_fn"]


def default_render_fn() -> Callable:
    """``renderworld.splat.rasterize``, imported on use (the library's rasterizer)."""
    from renderworld.splat import rasterize

    return rasterize


@dataclass
class RenderedViews:
    """Rendered cameras of a batch.

    Attributes:
        features: [B, C, H, W, K] blended class probabilities (sum = alpha), K = 17.
        depth: [B, C, H, W] expected camera-z depth normalised by alpha, metres.
        alpha: [B, C, H, W] accumulated opacity.
        num_rendered: [B] int64 Gaussians rendered per sample after pruning.
    """

    features: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    num_rendered: torch.Tensor


def render_views(
    gaussians: AnchorGaussians,
    cam_to_ego: torch.Tensor,
    intrinsics: torch.Tensor,
    width: int,
    height: int,
    render_fn: Callable | None = None,
    prune_opacity: float = 0.0,
    near: float = 0.1,
    far: float = 100.0,
    backend: str = "auto",
) -> RenderedViews:
    """Render class probabilities (softmax of the logits) and depth into C cameras per sample.

    Args:
        gaussians: :class:`AnchorGaussians` with batch size B.
        cam_to_ego: [B, C, 4, 4] camera → keyframe-ego transforms.
        intrinsics: [B, C, 3, 3] intrinsics at the render size (pixels).
        width: render width W (pixels).
        height: render height H (pixels).
        render_fn: a function with ``renderworld.splat.rasterize``'s signature; default that.
        prune_opacity: render only Gaussians with opacity > this (detached selection).
        near: near plane, metres.
        far: far plane, metres.
        backend: rasterizer backend name passed through.

    Returns:
        :class:`RenderedViews`.
    """
    b, v = gaussians.opacities.shape
    if cam_to_ego.ndim != 4 or cam_to_ego.shape[0] != b or cam_to_ego.shape[2:] != (4, 4):
        raise ValueError(f"cam_to_ego: expected [{b}, C, 4, 4], got {tuple(cam_to_ego.shape)}")
    c = cam_to_ego.shape[1]
    if intrinsics.shape != (b, c, 3, 3):
        raise ValueError(f"intrinsics: expected {(b, c, 3, 3)}, got {tuple(intrinsics.shape)}")
    if render_fn is None:
        render_fn = default_render_fn()
    dtype = gaussians.means.dtype
    viewmats = invert_pose(cam_to_ego.to(dtype))
    probs = torch.softmax(gaussians.logits, dim=-1)
    feats, depths, alphas, counts = [], [], [], []
    k = NUM_SEMANTIC_CLASSES
    for i in range(b):
        keep = torch.nonzero(gaussians.opacities[i].detach() > prune_opacity)[:, 0]
        counts.append(keep.numel())
        if keep.numel() == 0:
            # Nothing to draw: an empty image that is still part of the graph.
            zero = gaussians.opacities[i].sum() * 0 + probs[i].sum() * 0
            feats.append(zero + probs.new_zeros(c, height, width, k))
            depths.append(zero + probs.new_zeros(c, height, width))
            alphas.append(zero + probs.new_zeros(c, height, width))
            continue
        args = dict(
            means=gaussians.means[i, keep],
            quats=gaussians.quats[i, keep],
            scales=gaussians.scales[i, keep],
            opacities=gaussians.opacities[i, keep],
            width=width,
            height=height,
            near=near,
            far=far,
            backend=backend,
        )
        out = render_fn(
            features=probs[i, keep], viewmats=viewmats[i], Ks=intrinsics[i].to(dtype), **args
        )
        feats.append(out.features)
        depths.append(out.depth)
        alphas.append(out.alpha)
    return RenderedViews(
        features=torch.stack(feats),
        depth=torch.stack(depths),
        alpha=torch.stack(alphas),
        num_rendered=torch.tensor(counts, dtype=torch.long),
    )
