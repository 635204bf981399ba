"""The rasterizer's result type, shared by the public entry point and every backend."""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["RenderResult", "DEPTH_EPS"]

#: Accumulated alpha below which expected depth is reported as 0.
DEPTH_EPS = 1e-10


class RenderResult(NamedTuple):
    """Rendered images.

    Attributes:
        features: [C, H, W, D] un-normalised ``Σ_i f_i α_i T_i`` (as gsplat; divide by ``alpha``
            for the normalised feature, or add a background ``(1 - alpha)·bg``).
        depth: [C, H, W] expected camera-z depth (metres), ``Σ z_i α_i T_i / alpha``; exactly 0
            where no Gaussian contributes (alpha == 0).
        alpha: [C, H, W] accumulated opacity ``Σ α_i T_i = 1 - T_final`` in [0, 1).
    """

    features: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
