"""Tile binning: which projected Gaussians touch which screen tiles, depth-sorted per tile.

A Gaussian touches a tile when its opacity-aware box (the exact axis-aligned box of the
alpha >= ALPHA_MIN ellipse, :attr:`ProjectedGaussians.extents`) contains a pixel centre of that
tile, so skipping the other tiles never changes the image. Intersections are sorted by
(camera, tile, depth rank) with a single int64 sort; depth ties keep Gaussian index order, the
same order the dense reference uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from renderworld.splat.projection import ProjectedGaussians

__all__ = ["TileBins", "bin_gaussians"]


@dataclass
class TileBins:
    """Sorted tile–Gaussian intersections.

    Attributes:
        tile_size: tile side (pixels).
        tiles_x: tiles per image row; ``tiles_y`` tiles per column.
        tiles_y: tiles per image column.
        pair_ids: [M] int64 row of :class:`ProjectedGaussians` per intersection, sorted by
            (camera, tile, depth).
        tile_offsets: [C * tiles_y * tiles_x + 1] int64; intersections of flat tile t (camera
            ``t // (tiles_x * tiles_y)``) are ``pair_ids[tile_offsets[t]:tile_offsets[t + 1]]``.
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    pair_ids: torch.Tensor
    tile_offsets: torch.Tensor


def bin_gaussians(
    proj: ProjectedGaussians, num_cams: int, width: int, height: int, tile_size: int
) -> TileBins:
    """Bin projected Gaussians into ``tile_size`` tiles (no gradient).

    Args:
        proj: projection of N Gaussians into C cameras (V pairs).
        num_cams: C.
        width: image width (pixels).
        height: image height (pixels).
        tile_size: tile side (pixels), > 0.

    Returns:
        :class:`TileBins`.
    """
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    device = proj.cam_ids.device
    with torch.no_grad():
        num_pairs = len(proj)
        cam = proj.cam_ids
        uv = proj.means2d.detach().double()
        ext = proj.extents.double()
        # Pixel columns i whose centre i + 0.5 lies in [u - ex, u + ex], clamped to the image.
        lo = torch.ceil(uv - ext - 0.5)
        hi = torch.floor(uv + ext - 0.5)
        lo_x = lo[:, 0].clamp(0, width - 1).long() // tile_size
        hi_x = hi[:, 0].clamp(0, width - 1).long() // tile_size
        lo_y = lo[:, 1].clamp(0, height - 1).long() // tile_size
        hi_y = hi[:, 1].clamp(0, height - 1).long() // tile_size
        nx = (hi_x - lo_x + 1).clamp_min(0)
        ny = (hi_y - lo_y + 1).clamp_min(0)
        counts = nx * ny
        # Depth rank over all valid pairs (stable: ties keep index order).
        rank = torch.empty_like(cam)
        rank[torch.sort(proj.depths.detach(), stable=True).indices] = torch.arange(
            num_pairs, device=device
        )
        owner = torch.repeat_interleave(torch.arange(num_pairs, device=device), counts)
        starts = torch.cumsum(counts, 0) - counts
        local = torch.arange(owner.numel(), device=device) - starts[owner]
        # local = row * nx + col; small integers (< tiles per image), so float division is
        # exact and much cheaper than int64 division.
        width_o = nx[owner].to(torch.float32)
        row_o = torch.floor((local.to(torch.float32) + 0.5) / width_o)
        col_o = local - (row_o * width_o).long()
        tx = lo_x[owner] + col_o
        ty = lo_y[owner] + row_o.long()
        tile = (cam[owner] * tiles_y + ty) * tiles_x + tx
        key = tile * (num_pairs + 1) + rank[owner]
        pair_ids = owner[torch.sort(key).indices]
        num_tiles = num_cams * tiles_y * tiles_x
        per_tile = torch.bincount(tile, minlength=num_tiles)
        tile_offsets = torch.zeros(num_tiles + 1, dtype=torch.long, device=device)
        tile_offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(tile_size, tiles_x, tiles_y, pair_ids, tile_offsets)
