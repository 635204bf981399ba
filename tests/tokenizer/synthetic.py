"""Synthetic occupancy volumes for the tokenizer tests: a street scene on a small grid.

A ground layer (driveable surface along a road band, sidewalks beside it, terrain outside),
boxes of cars on the road, buildings (manmade) and trees (vegetation trunk + canopy) off the
road; everything else is free. Class ids come from ``renderworld.constants``.
"""

from __future__ import annotations

import torch

from renderworld.constants import FREE_ID, OCC3D_CLASSES

ROAD = OCC3D_CLASSES.index("driveable_surface")
SIDEWALK = OCC3D_CLASSES.index("sidewalk")
TERRAIN = OCC3D_CLASSES.index("terrain")
CAR = OCC3D_CLASSES.index("car")
BUILDING = OCC3D_CLASSES.index("manmade")
TREE = OCC3D_CLASSES.index("vegetation")


def street_scene(shape: tuple[int, int, int] = (32, 32, 8), seed: int = 0) -> torch.Tensor:
    """One synthetic volume.

    Args:
        shape: (X, Y, Z) with X, Y >= 16 and Z >= 4.
        seed: Generator seed.

    Returns:
        [X, Y, Z] uint8 Occ3D ids.
    """
    g = torch.Generator().manual_seed(seed)
    X, Y, Z = shape

    def r(lo: int, hi: int) -> int:  # uniform in [lo, hi), lo when the range is empty
        return int(torch.randint(lo, max(hi, lo + 1), (1,), generator=g))

    occ = torch.full(shape, FREE_ID, dtype=torch.uint8)
    road_w, y0 = r(X // 6, X // 3), r(Y // 4, Y // 2)
    occ[:, :, 0] = TERRAIN
    occ[:, max(0, y0 - 2) : y0 + road_w + 2, 0] = SIDEWALK
    occ[:, y0 : y0 + road_w, 0] = ROAD
    for _ in range(r(1, 4)):  # cars on the road, 4 x 2 x 2 voxels
        x, y = r(0, X - 4), r(y0, max(y0 + 1, y0 + road_w - 2))
        occ[x : x + 4, y : y + 2, 1:3] = CAR
    for _ in range(r(1, 3)):  # buildings outside the road band
        w, d, h = r(3, 7), r(3, 6), r(3, Z)
        x = r(0, X - w)
        y = r(0, max(1, y0 - 2 - d)) if r(0, 2) == 0 else r(y0 + road_w + 2, Y - d + 1)
        occ[x : x + w, y : y + d, 1 : 1 + h] = BUILDING
    for _ in range(r(1, 4)):  # trees: a trunk and a 3 x 3 canopy
        x, y = r(1, X - 2), r(1, Y - 2)
        if occ[x, y, 0] == ROAD:
            continue
        occ[x, y, 1:3] = TREE
        occ[x - 1 : x + 2, y - 1 : y + 2, 3 : min(Z, 5)] = TREE
    return occ


def street_batch(n: int, shape=(32, 32, 8), seed: int = 0) -> torch.Tensor:
    """[n, X, Y, Z] uint8 stack of :func:`street_scene` volumes with seeds seed..seed+n-1."""
    return torch.stack([street_scene(shape, seed + i) for i in range(n)])
