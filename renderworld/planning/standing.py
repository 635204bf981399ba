"""What stands in the forecast, and a shorter IDM headway behind it.

IDM's time headway (``CheckConfig.headway``, 1.5 s) is the room a follower keeps for its leader
braking. An obstacle that stands cannot brake: a parked car, a car stopped in a queue, static
scenery. Behind it the full headway only makes the ego brake early and long, which in an
overtake means standing behind a parked car that the learned plan was about to steer round.
With :attr:`~renderworld.planning.candidates.CheckConfig.standing_headway` the IDM time headway
behind a standing vehicle on the road ahead is that value instead: one the tracker saw standing
over the history (:attr:`~renderworld.world.tracks.MoverTrack.moving` false), that the forecast
moves less than :data:`STANDING_M` over the horizon, and that the path reaches over drivable
cells only (up to :data:`REACH_BEFORE_M` before its centroid), while the ego drives at
``CheckConfig.standing_min_speed`` or faster. Everything else keeps the full headway: a lead
car that has just braked to a stop (it drives off again, and time to collision is judged on its
logged motion), a standing pedestrian or two-wheeler (it may step or pull off at once), every
mover that moves, static scenery, a car parked beside a bend, which only the straight extension
of the path beyond the plan's end meets after leaving the road, and every standing vehicle
while the ego crawls (then the headway only decides how close it creeps up behind a car that
may drive off).

Frames: the current ego frame (x forward, y left; metres, seconds).
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import VULNERABLE_CLASS_IDS
from renderworld.planning.path import PlanPath
from renderworld.planning.scene import ForecastScene

__all__ = ["REACH_BEFORE_M", "STANDING_M", "mover_travel", "moving_points", "standing_headways"]

#: metres: a mover forecast to move less than this over the horizon stands.
STANDING_M = 1.0
#: metres: the path must run on drivable cells up to this far short of a standing vehicle's
#: centroid (about half a car's length: its own cells count as drivable).
REACH_BEFORE_M = 2.0


def mover_travel(scene: ForecastScene) -> np.ndarray:
    """[M] metres each mover travels along its forecast displacement over the horizon."""
    disp = scene.displacements  # [M, S + 1, 2]
    if not len(disp):
        return np.zeros(0)
    return np.hypot(*(disp[:, 1:] - disp[:, :-1]).transpose(2, 0, 1)).sum(-1)


def moving_points(scene: ForecastScene) -> np.ndarray:
    """[P] bool: the scene's points of a mover forecast to move :data:`STANDING_M` or more."""
    travel = mover_travel(scene)
    if not len(travel):
        return np.zeros(len(scene.points), dtype=bool)
    return (scene.mover >= 0) & (travel[np.maximum(scene.mover, 0)] >= STANDING_M)


def standing_headways(
    scene: ForecastScene,
    path: PlanPath,
    cfg,
    mover_headway: np.ndarray | None = None,
    speed: float = np.inf,
) -> np.ndarray | None:
    """[M] the IDM time headway (seconds) behind each of the scene's movers: ``mover_headway``
    (None: ``cfg.headway``), lowered to ``cfg.standing_headway`` behind each standing vehicle
    (module docstring; an entrant's shorter headway is kept); ``mover_headway`` itself where
    ``cfg.standing_headway`` is None or the ego is slower than ``cfg.standing_min_speed``.

    Args:
        scene: the forecast scene (its tracks' classes, its movers' displacements).
        path: the plan's path (current ego frame).
        cfg: the :class:`~renderworld.planning.candidates.CheckConfig`.
        mover_headway: None, or [M] headways already set (e.g. an entrant's, seconds).
        speed: the ego's speed now, m/s.
    """
    m = len(scene.displacements)
    if cfg.standing_headway is None or m == 0 or speed < cfg.standing_min_speed:
        return mover_headway
    hw = (
        np.full(m, float(cfg.headway))
        if mover_headway is None
        else np.asarray(mover_headway, dtype=np.float64).copy()
    )
    stood = np.array([tr.cls not in VULNERABLE_CLASS_IDS and not tr.moving
                      for tr in scene.tracks[:m]], dtype=bool)  # fmt: skip
    stands = stood & (mover_travel(scene) < STANDING_M)
    idx = np.flatnonzero(stands)
    if len(idx):
        arcs = path.frenet(np.stack([scene.tracks[i].centroid for i in idx]).astype(np.float64))[0]
        for i, arc in zip(idx, arcs, strict=True):
            on_road = path.at(np.arange(0.0, max(arc - REACH_BEFORE_M, 0.0) + 1e-9, 1.0))[0]
            stands[i] = bool(scene.on_drivable(on_road).all())
    hw[stands] = np.minimum(hw[stands], float(cfg.standing_headway))
    return hw
