"""Small random scenes and cameras for the rasterizer tests."""

from __future__ import annotations

import torch

from renderworld.splat import available_backends

#: Fast implementations compared with the dense reference (the ``cpp`` kernel when it compiles).
FAST_IMPLS = [b for b in ("torch", "cpp") if b in available_backends("cpu")]
ALL_IMPLS = ["reference"] + FAST_IMPLS


def look_at_cameras(num_cams: int = 2, dtype=torch.float64):
    """Cameras looking down +z from around the origin; world = camera 0 frame.

    Returns:
        ``(viewmats [C, 4, 4], Ks [C, 3, 3])`` for a 40 x 30 image.
    """
    viewmats = torch.eye(4, dtype=dtype).repeat(num_cams, 1, 1)
    for c in range(1, num_cams):
        angle = torch.tensor(0.15 * c, dtype=dtype)
        viewmats[c, 0, 0] = torch.cos(angle)
        viewmats[c, 0, 2] = -torch.sin(angle)
        viewmats[c, 2, 0] = torch.sin(angle)
        viewmats[c, 2, 2] = torch.cos(angle)
        viewmats[c, 0, 3] = 0.3 * c
    Ks = torch.tensor([[32.0, 0, 20.0], [0, 30.0, 15.0], [0, 0, 1]], dtype=dtype).repeat(
        num_cams, 1, 1
    )
    return viewmats, Ks


WIDTH, HEIGHT = 40, 30


def random_scene(n: int, dim: int = 3, seed: int = 0, dtype=torch.float64, depth=8.0, spread=2.5):
    """Random Gaussians in front of :func:`look_at_cameras`.

    Returns:
        ``[means [N, 3], quats [N, 4], scales [N, 3], opacities [N], features [N, D]]``.
    """
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * spread
    means[:, 2] = depth + torch.rand(n, generator=g, dtype=dtype) * 6 - 3
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = 0.05 + 0.4 * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=dtype)
    features = torch.randn(n, dim, generator=g, dtype=dtype)
    return [means, quats, scales, opacities, features]


def render(params, backend, viewmats=None, Ks=None, width=WIDTH, height=HEIGHT, **kw):
    """Call :func:`renderworld.splat.rasterize` with test cameras by default."""
    from renderworld.splat import rasterize

    if viewmats is None:
        viewmats, Ks = look_at_cameras(2, params[0].dtype)
    return rasterize(*params, viewmats, Ks, width, height, backend=backend, **kw)


def loss_of(result, seed: int = 123):
    """A fixed random linear functional of all outputs (features, depth, alpha)."""
    g = torch.Generator().manual_seed(seed)
    total = 0.0
    for t in result:
        w = torch.randn(t.shape, generator=g, dtype=t.dtype)
        total = total + (t * w).sum()
    return total


def grads(params, backend, **kw):
    """Outputs and gradients of :func:`loss_of` with respect to the five parameters."""
    leaves = [p.detach().clone().requires_grad_(True) for p in params]
    out = render(leaves, backend, **kw)
    loss_of(out).backward()
    return out, [p.grad for p in leaves]
