"""Differentiable Gaussian rasterization of features, expected depth and alpha.

``rasterize`` is the one public entry point; backends share its contract (see
:func:`renderworld.splat.api.rasterize`): ``reference`` (dense oracle), ``torch`` (tiled pure
torch), ``cpp`` (tiled C++/OpenMP CPU kernel, compiled on first use) and ``gsplat`` (CUDA).
"""

from renderworld.splat.api import BACKENDS, RenderResult, available_backends, rasterize
from renderworld.splat.projection import (
    ALPHA_MAX,
    ALPHA_MIN,
    EPS2D,
    TRANSMITTANCE_MIN,
    ProjectedGaussians,
    project_gaussians,
    quat_to_rotmat,
)

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "BACKENDS",
    "EPS2D",
    "TRANSMITTANCE_MIN",
    "ProjectedGaussians",
    "RenderResult",
    "available_backends",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
]
