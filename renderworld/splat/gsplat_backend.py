"""The ``gsplat`` backend: CUDA rasterization through gsplat (imported lazily, only on use).

gsplat follows the same conventions (pixel centres at i + 0.5, EWA with a 0.3 px² low-pass,
1/255 skip, transmittance stop at 1e-4, camera-z depth). Known differences from the CPU
backends, kept small by the arguments below: gsplat bounds each Gaussian by a 3σ-ish radius
(the CPU backends use the exact opacity-aware box), and older gsplat releases clamp alpha at
0.999 instead of 0.99. Its ``"RGB+D"`` mode gives accumulated (un-normalised) depth, which is
normalised here exactly as for the other backends.
"""

from __future__ import annotations

import torch

from renderworld.splat.projection import EPS2D
from renderworld.splat.result import DEPTH_EPS, RenderResult

__all__ = ["rasterize_gsplat"]


def rasterize_gsplat(
    means, quats, scales, opacities, features, viewmats, Ks, width, height, near, far
):
    """Rasterize with ``gsplat.rasterization`` (contract of :func:`renderworld.splat.rasterize`).

    Returns:
        :class:`renderworld.splat.RenderResult` on the inputs' CUDA device.
    """
    import gsplat  # lazy: an optional CUDA-only dependency (imports CUDA on import)

    # Zero quaternions are a reported NaN source in gsplat: give them the identity rotation (the
    # CPU backends' limit, with a zero gradient there too).
    norm2 = (quats * quats).sum(-1, keepdim=True)
    identity = torch.zeros_like(quats)
    identity[:, 0] = 1.0
    quats = torch.where(norm2 > 1e-24, quats, identity)
    colors, alphas, _ = gsplat.rasterization(
        means,
        quats,
        scales,
        opacities,
        features,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near,
        far_plane=far,
        eps2d=EPS2D,
        sh_degree=None,
        packed=False,
        render_mode="RGB+D",
    )
    dim = features.shape[1]
    alpha = alphas[..., 0]
    depth = colors[..., dim] / alpha.clamp_min(DEPTH_EPS)
    return RenderResult(colors[..., :dim], depth, alpha)
