"""Dense reference rasterizer: every pixel against every Gaussian, plain torch autograd.

This is the test oracle of the fast backends. It evaluates all pixel–Gaussian pairs of a camera
(in pixel chunks, each recomputed in backward through activation checkpointing so memory stays
bounded), composites front to back in depth order with log-space transmittance, and implements the
same rules as the tiled backends: alpha = min(ALPHA_MAX, opacity·exp(-½ dᵀΣ'⁻¹d)), pairs with
alpha < ALPHA_MIN skipped, a pixel stops before the Gaussian that would bring its transmittance
to <= TRANSMITTANCE_MIN. Works in float32 and float64; use it on small inputs only.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from renderworld.splat.projection import (
    ALPHA_MAX,
    ALPHA_MIN,
    log_alpha_cut,
    pixel_centres,
    project_gaussians,
)

__all__ = ["rasterize_reference", "composite_dense"]


def composite_dense(
    pix: torch.Tensor,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite depth-sorted Gaussians over a set of pixels.

    Args:
        pix: [P, 2] pixel centres (u, v).
        means2d: [G, 2] projected centres, sorted front to back.
        conics: [G, 3] inverse 2D covariances (a, b, c).
        opacities: [G] opacities.
        colors: [G, K] values to composite (features, then depth, in one tensor).

    Returns:
        ``(out [P, K] = Σ w_i colors_i, alpha [P] = Σ w_i)`` with ``w_i = alpha_i·T_i``.
    """
    d = pix[:, None, :] - means2d[None, :, :]  # [P, G, 2]
    dx, dy = d[..., 0], d[..., 1]
    power = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = (opacities * torch.exp(-power.clamp_min(0.0))).clamp_max(ALPHA_MAX)
    alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
    log1m = torch.log1p(-alpha)
    log_t_after = torch.cumsum(log1m, dim=1)
    keep = log_t_after > log_alpha_cut()  # prefix along G: transmittance is non-increasing
    weights = alpha * torch.exp(log_t_after - log1m) * keep
    return weights @ colors, weights.sum(1)


def rasterize_reference(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    pixel_chunk: int = 4096,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dense rasterization (see :func:`renderworld.splat.rasterize` for the contract).

    Args:
        means, quats, scales, opacities, features, viewmats, Ks, width, height, near, far: as in
            :func:`renderworld.splat.rasterize` (validated there).
        pixel_chunk: pixels evaluated at once per camera; each chunk is checkpointed when
            gradients are needed, so peak memory is about ``pixel_chunk · N`` pairs.

    Returns:
        ``(features [C, H, W, D] un-normalised, depth_sum [C, H, W] = Σ w_i z_i,
        alpha [C, H, W])``; the caller normalises depth.
    """
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height, near, far
    )
    num_cams, dim = viewmats.shape[0], features.shape[1]
    pix = pixel_centres(width, height, means.dtype, means.device).reshape(-1, 2)
    feats, depths, alphas = [], [], []
    for cam in range(num_cams):
        rows = torch.nonzero(proj.cam_ids == cam).squeeze(1)  # ordered by Gaussian index
        order = rows[torch.sort(proj.depths[rows].detach(), stable=True).indices]
        gid = proj.gauss_ids[order]
        m2d, con = proj.means2d[order], proj.conics[order]
        colors = torch.cat([features[gid], proj.depths[order, None]], dim=1)
        op = opacities[gid]
        outs, accs = [], []
        for start in range(0, pix.shape[0], pixel_chunk):
            chunk = pix[start : start + pixel_chunk]
            if torch.is_grad_enabled() and order.numel() > 0:
                out, acc = checkpoint(
                    composite_dense, chunk, m2d, con, op, colors, use_reentrant=False
                )
            else:
                out, acc = composite_dense(chunk, m2d, con, op, colors)
            outs.append(out)
            accs.append(acc)
        out = torch.cat(outs).reshape(height, width, dim + 1)
        feats.append(out[..., :dim])
        depths.append(out[..., dim])
        alphas.append(torch.cat(accs).reshape(height, width))
    return torch.stack(feats), torch.stack(depths), torch.stack(alphas)
