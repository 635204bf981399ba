"""Tiled rasterizer in pure torch (the ``torch`` backend, twin and oracle of the ``cpp`` kernel).

Pipeline: EWA projection (:mod:`projection`) → cull → bin to tiles by the opacity-aware box
(:mod:`binning`) → composite every tile's depth-sorted list in chunks of Gaussians, all tiles of
a round at once; the first chunk has ``chunk`` Gaussians and each next one twice as many (up to
``8 * chunk``), so tiles that terminate early pay little and long lists take few rounds. A tile
leaves the loop when its list is exhausted or all its pixels terminated (transmittance would
fall to <= TRANSMITTANCE_MIN). Transmittance is accumulated in log space. Each round is
checkpointed when gradients are needed, so autograd memory is bounded by the round outputs
instead of every pixel–Gaussian pair (recomputing a round in backward is the price).
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from renderworld.splat.binning import TileBins, bin_gaussians
from renderworld.splat.projection import (
    ALPHA_MAX,
    ALPHA_MIN,
    log_alpha_cut,
    project_gaussians,
)

__all__ = ["rasterize_tiled", "TILE_SIZE"]

#: Default tile side (pixels), as gsplat.
TILE_SIZE = 16


def _round(
    pix_u: torch.Tensor,
    pix_v: torch.Tensor,
    log_t0: torch.Tensor,
    done: torch.Tensor,
    m2d: torch.Tensor,
    con: torch.Tensor,
    op: torch.Tensor,
    colors: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite one chunk of depth-sorted Gaussians over the pixels of several tiles.

    Args:
        pix_u, pix_v: [Ta, P] pixel centres.
        log_t0: [Ta, P] log transmittance before the chunk.
        done: [Ta, P] bool, pixels already terminated (or outside the image).
        m2d: [Ta, B, 2] means; con: [Ta, B, 3] conics; op: [Ta, B] opacities (0 for padding).
        colors: [Ta, B, K] values to composite.

    Returns:
        ``(contrib [Ta, P, K], log_t1 [Ta, P], done1 [Ta, P])``.
    """
    dx = pix_u[:, :, None] - m2d[:, None, :, 0]
    dy = pix_v[:, :, None] - m2d[:, None, :, 1]
    a, b, c = (con[:, None, :, i] for i in range(3))
    power = (0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy).clamp_min(0.0)
    alpha = (op[:, None, :] * torch.exp(-power)).clamp_max(ALPHA_MAX)
    use = (alpha >= ALPHA_MIN) & ~done[:, :, None]
    alpha = torch.where(use, alpha, torch.zeros_like(alpha))
    log1m = torch.log1p(-alpha)
    log_t_after = log_t0[:, :, None] + torch.cumsum(log1m, dim=2)
    keep = log_t_after > log_alpha_cut()
    weights = alpha * torch.exp(log_t_after - log1m) * keep
    contrib = torch.bmm(weights, colors)
    log_t1 = log_t0 + (log1m * keep).sum(2)
    done1 = done | ~keep.all(2)
    return contrib, log_t1, done1


def composite_tiles(
    bins: TileBins,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    width: int,
    height: int,
    chunk: int = 32,
) -> torch.Tensor:
    """Composite binned Gaussians into images.

    Args:
        bins: tile intersections over the V projected pairs.
        means2d: [V, 2]; conics: [V, 3]; opacities: [V]; colors: [V, K] per pair.
        width, height: image size (pixels).
        chunk: Gaussians per tile in the first round (doubling each round, up to 8x).

    Returns:
        [C, H, W, K] ``Σ w_i colors_i``.
    """
    ts = bins.tile_size
    num_tiles = bins.tile_offsets.numel() - 1
    tiles_per_cam = bins.tiles_x * bins.tiles_y
    num_cams = num_tiles // tiles_per_cam
    device, dtype = means2d.device, means2d.dtype
    k_dim = colors.shape[1]
    offsets = bins.tile_offsets
    counts = offsets[1:] - offsets[:-1]

    pix_u_all, pix_v_all, done_all = _tile_pixels(bins, num_tiles, width, height, device, dtype)
    log_t_all = torch.zeros(num_tiles, ts * ts, dtype=dtype, device=device)

    ids, contribs = [], []
    active = torch.nonzero(counts > 0).squeeze(1)
    step = chunk
    start = 0
    grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, opacities, colors)
    )
    while active.numel() > 0:
        slot = start + torch.arange(step, device=device)[None, :]  # [Ta, B]
        present = slot < counts[active, None]
        pos = torch.where(present, offsets[active, None] + slot, torch.zeros_like(slot))
        gid = bins.pair_ids[pos]
        op = torch.where(present, opacities[gid], torch.zeros((), dtype=dtype, device=device))
        args = (
            pix_u_all[active],
            pix_v_all[active],
            log_t_all[active],
            done_all[active],
            means2d[gid],
            conics[gid],
            op,
            colors[gid],
        )
        if grad:
            contrib, log_t1, done1 = checkpoint(_round, *args, use_reentrant=False)
        else:
            contrib, log_t1, done1 = _round(*args)
        ids.append(active)
        contribs.append(contrib)
        log_t_all = log_t_all.index_copy(0, active, log_t1)
        done_all = done_all.index_copy(0, active, done1)
        start += step
        step = min(2 * step, 8 * chunk)
        alive = (counts[active] > start) & ~done1.all(1)
        active = active[alive]

    out = torch.zeros(num_tiles, ts * ts, k_dim, dtype=dtype, device=device)
    if ids:
        out = out.index_add(0, torch.cat(ids), torch.cat(contribs))
    elif grad:  # nothing visible: keep the (zero) outputs connected to the inputs' graph
        out = out + 0.0 * sum(t.sum() for t in (means2d, conics, opacities, colors))
    out = out.reshape(num_cams, bins.tiles_y, bins.tiles_x, ts, ts, k_dim)
    out = out.permute(0, 1, 3, 2, 4, 5).reshape(num_cams, bins.tiles_y * ts, bins.tiles_x * ts, -1)
    return out[:, :height, :width]


def _tile_pixels(bins: TileBins, num_tiles: int, width: int, height: int, device, dtype):
    """Pixel centres of every tile's pixels and which fall outside the image.

    Returns:
        ``(u [NT, P], v [NT, P], outside [NT, P])``: centres (i + 0.5, j + 0.5) in pixels of
        the P = tile_size² pixels of each of the NT tiles; ``outside`` marks padding pixels.
    """
    ts = bins.tile_size
    tile_idx = torch.arange(num_tiles, device=device)
    tx = tile_idx % bins.tiles_x
    ty = (tile_idx // bins.tiles_x) % bins.tiles_y
    local = torch.arange(ts * ts, device=device)
    col = tx[:, None] * ts + local % ts  # [NT, P]
    row = ty[:, None] * ts + local // ts
    return col.to(dtype) + 0.5, row.to(dtype) + 0.5, (col >= width) | (row >= height)


def rasterize_tiled(
    means,
    quats,
    scales,
    opacities,
    features,
    viewmats,
    Ks,
    width,
    height,
    near,
    far,
    tile_size: int = TILE_SIZE,
    chunk: int = 32,
):
    """Tiled pure-torch rasterization (contract of :func:`renderworld.splat.rasterize`).

    Returns:
        ``(features [C, H, W, D], depth_sum [C, H, W], alpha [C, H, W])``.
    """
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height, near, far
    )
    bins = bin_gaussians(proj, viewmats.shape[0], width, height, tile_size)
    gid = proj.gauss_ids
    ones = torch.ones_like(proj.depths)[:, None]
    colors = torch.cat([features[gid], proj.depths[:, None], ones], dim=1)
    out = composite_tiles(
        bins, proj.means2d, proj.conics, opacities[gid], colors, width, height, chunk
    )
    dim = features.shape[1]
    return out[..., :dim], out[..., dim], out[..., dim + 1]
