"""A shorter IDM headway behind a vehicle that has just entered the ego's corridor.

A driver cut in on accepts the short gap and opens it up over the next seconds instead of
braking at once to the full time headway (the headway relaxation of lane-change models, e.g.
Schakel, Knoop and van Arem's LMRS, 2012). IDM at its full headway brakes hard for a car that
enters 8 m ahead at the ego's own speed (``s*`` = 2 m + 1.5 s x 10 m/s against an 8 m gap:
over 6 m/s^2 at its peak, ``tests/planning/test_relax.py``). With
:attr:`~renderworld.planning.candidates.CheckConfig.entrant_headway` the IDM time headway
behind a vehicle that the tracker saw outside the corridor of the plan's path within the last
``entrant_relax_s`` seconds of the history is ``entrant_headway + (headway - entrant_headway) x
tau / entrant_relax_s``, ``tau`` the seconds since the history frame in which it was last seen
outside (0 while it is outside now, about to cut in).
Only a vehicle that drives the ego's way counts (its fitted velocity at least
:data:`ALONG_MPS` along the path and more along it than across it): an oncoming or crossing car,
a pedestrian or a two-wheeler keeps the full headway, and so does a vehicle that was in the
corridor all along (a lead car braking): the margin its late forecast needs.

Frames: the current ego frame (x forward, y left; metres, seconds).
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import EGO_WIDTH, VULNERABLE_CLASS_IDS
from renderworld.planning.path import PlanPath
from renderworld.planning.scene import ForecastScene
from renderworld.world.tracks import cell_xy

__all__ = ["ALONG_MPS", "entrant_headways"]

#: Least speed along the path (m/s) of a vehicle whose entry relaxes the headway.
ALONG_MPS = 2.0


def entrant_headways(scene: ForecastScene, path: PlanPath, cfg) -> np.ndarray | None:
    """[M] the IDM time headway (seconds) behind each of the scene's movers (module docstring),
    or None where ``cfg.entrant_headway`` is None (every mover: ``cfg.headway``).

    A mover is in the corridor in a history frame when its footprint (its current cells,
    carried with its centroid) overlaps, across the path, the ego's half-width and
    ``cfg.corridor_margin_m`` on either side of ``path`` (the unshifted path).

    Args:
        scene: the forecast scene (its tracks: classes, cells, centroids over the history).
        path: the plan's path.
        cfg: the :class:`~renderworld.planning.candidates.CheckConfig`.
    """
    m = len(scene.displacements)
    if cfg.entrant_headway is None or m == 0:
        return None
    hw = np.full(m, float(cfg.headway))
    half = EGO_WIDTH / 2 + cfg.corridor_margin_m
    for i, tr in enumerate(scene.tracks[:m]):
        if tr.cls in VULNERABLE_CLASS_IDS or not tr.cells.any():
            continue
        arc, lat = path.frenet(np.asarray(tr.centroids, dtype=np.float64))  # [K], newest first
        h = float(path.at(arc[0])[1])
        vx, vy = (float(c) for c in tr.velocity)
        along, across = vx * np.cos(h) + vy * np.sin(h), -vx * np.sin(h) + vy * np.cos(h)
        if along < ALONG_MPS or abs(across) > along:
            continue
        lat_cells = path.frenet(cell_xy(tr.cells, scene.grid))[1]
        lo, hi = lat_cells.min() - lat[0], lat_cells.max() - lat[0]
        inside = (lat + hi >= -half) & (lat + lo <= half)
        if inside.all():
            continue
        since = -float(np.asarray(tr.times)[np.flatnonzero(~inside)[0]])  # last seen outside
        if since >= cfg.entrant_relax_s:
            continue
        frac = since / cfg.entrant_relax_s
        hw[i] = cfg.entrant_headway + (cfg.headway - cfg.entrant_headway) * frac
    return hw
