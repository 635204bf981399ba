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
        moments: [B, C, H, W, 2] ``(sum_i w_i z_i, sum_i w_i z_i^2)`` of the blending
            weights w_i and the Gaussians' camera z (metres, m^2), when rendered with
            ``depth_moments=True`` (else None).
    """

    features: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    num_rendered: torch.Tensor
    moments: torch.Tensor | None = None


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
    depth_moments: bool = False,
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
        depth_moments: also render the first two moments of the Gaussians' camera z under
            the blending weights (``RenderedViews.moments``); z differs per camera, so each
            camera is rasterized on its own with the two extra feature channels.

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
    feats, depths, alphas, moments, counts = [], [], [], [], []
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
            moments.append(zero + probs.new_zeros(c, height, width, 2))
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
        if not depth_moments:
            out = render_fn(
                features=probs[i, keep], viewmats=viewmats[i], Ks=intrinsics[i].to(dtype), **args
            )
            feats.append(out.features)
            depths.append(out.depth)
            alphas.append(out.alpha)
            continue
        per_cam = []
        for j in range(c):
            rot, trans = viewmats[i, j, :3, :3], viewmats[i, j, :3, 3]
            z = args["means"] @ rot[2] + trans[2]  # [N] camera z of the Gaussian centres
            f = torch.cat([probs[i, keep], z[:, None], (z * z)[:, None]], dim=1)
            per_cam.append(
                render_fn(
                    features=f,
                    viewmats=viewmats[i, j : j + 1],
                    Ks=intrinsics[i, j : j + 1].to(dtype),
                    **args,
                )
            )
        feats.append(torch.cat([o.features[..., :k] for o in per_cam]))
        depths.append(torch.cat([o.depth for o in per_cam]))
        alphas.append(torch.cat([o.alpha for o in per_cam]))
        moments.append(torch.cat([o.features[..., k:] for o in per_cam]))
    return RenderedViews(
        features=torch.stack(feats),
        depth=torch.stack(depths),
        alpha=torch.stack(alphas),
        num_rendered=torch.tensor(counts, dtype=torch.long),
        moments=torch.stack(moments) if depth_moments else None,
    )
