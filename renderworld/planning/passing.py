"""Passing a parked road user: candidates that leave the lane around it and a way back.

The learned plan does not swerve around a car parked in its lane, and the checker's small
lateral offsets (:attr:`~renderworld.planning.candidates.CheckConfig.offsets_m`, reached over
12 m) neither clear it nor are comfortable at the full width of a lane: the plan is held back
behind it and waits. With :attr:`CheckConfig.pass_parked` the checker also proposes, when a
parked road user stands in the plan's corridor ahead, the plan's path shifted just far enough
to clear it on either side, reached smoothly (a quintic smoothstep, no curvature jump) over the
distance the ego covers in :attr:`CheckConfig.pass_ramp_s` (as the logged drivers do), and IDM
runs along it. They are scored as every other candidate (the forecast movers in the next lane,
the drivable surface, comfort); a pass gives up no score for its offset and is not held off by
``plan_margin``: waiting behind a car that will not move is no progress.

Re-planned every step, the offset is measured from the path to the parked car's side each time,
so a pass under way keeps aiming at the same place beside it; once the car is behind the front
bumper there is nothing to pass and the learned plan takes the car back.

Parked: a car, truck, bus, trailer or construction vehicle (not a pedestrian or a two-wheeler)
that stood still over at least :attr:`CheckConfig.pass_parked_s` of the history, or that the
forecast moves less than 1 m. The offset clears every such road user and all static scenery
near it: the free space beside it, whatever the occupancy merged into one component.

Frames: the current ego frame (x forward, y left; metres, seconds, m/s), as
:mod:`renderworld.planning.candidates`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from renderworld.constants import EGO_WIDTH
from renderworld.planning.idm import FRONT, idm_arc, leaders
from renderworld.planning.scene import ForecastScene

__all__ = ["Blocker", "parked_blocker", "pass_candidates"]

_STAYS_M = 1.0  # a forecast displacement below this keeps a mover parked, metres
_LENGTH_M = 10.0  # what stands this far beyond the nearest standing point is passed too, metres
_STEP_M = 0.25  # lateral offsets tried, metres apart


@dataclass(frozen=True)
class Blocker:
    """A standing road user in the corridor ahead, and where the ego box would clear it.

    Attributes:
        gap_m: from the ego's front bumper to its nearest point along the path, metres.
        left: the least lateral offset to the left (+) whose shifted ego box clears every
            obstacle there by the clearance, metres; None if none within the limit.
        right: the same to the right (negative), metres; None if none.
    """

    gap_m: float
    left: float | None
    right: float | None


def _standing(scene: ForecastScene, parked_s: float) -> np.ndarray:
    """[P] bool: points of road users (not pedestrians or two-wheelers) that stood still over
    at least ``parked_s`` seconds of the history, or that the forecast leaves within
    :data:`_STAYS_M` of where they are now."""
    stays = np.ones(len(scene.points), dtype=bool)
    if len(scene.displacements):
        moved = np.hypot(*scene.displacements[:, -1].T) > _STAYS_M  # [M]
        stood = np.array([not tr.moving and float(np.min(tr.times)) <= -parked_s
                          for tr in scene.tracks], dtype=bool)  # fmt: skip
        moved &= ~stood[: len(moved)]
        tracked = scene.mover >= 0
        stays[tracked] = ~moved[scene.mover[tracked]]
    return scene.agent & ~scene.vulnerable & stays


def parked_blocker(scene: ForecastScene, path, speed: float, cfg) -> Blocker | None:
    """The standing road users ahead in the corridor of ``path`` (the ego's width and
    ``cfg.corridor_margin_m`` on each side), from the nearest one's point within
    ``cfg.pass_range_s`` at the ego's speed (at least 3 m/s) ahead of the front bumper; None
    if none. The offsets that clear it are the least, on either side, at which the shifted ego
    box (half its width and ``cfg.pass_clearance_m``) holds no point of a standing road user
    or of static scenery from there to :data:`_LENGTH_M` beyond: free space, whatever the
    occupancy merged into one component.

    Args:
        scene: the forecast scene.
        path: the plan's :class:`~renderworld.planning.path.PlanPath`.
        speed: the ego's speed now, m/s.
        cfg: the :class:`~renderworld.planning.candidates.CheckConfig`.
    """
    if not len(scene.points):
        return None
    half = EGO_WIDTH / 2 + cfg.corridor_margin_m
    arc, lat = path.frenet(scene.points)
    gap = arc - FRONT
    standing = _standing(scene, cfg.pass_parked_s)
    inside = standing & (np.abs(lat) <= half) & (gap > 0.0)
    inside &= gap < cfg.pass_range_s * max(speed, 3.0)
    if not inside.any():
        return None
    g0 = float(gap[inside].min())
    there = (standing | (scene.mover < 0)) & (gap >= g0 - 1.0) & (gap <= g0 + _LENGTH_M)
    lat_there = lat[there]
    clear = EGO_WIDTH / 2 + cfg.pass_clearance_m
    tried = np.arange(1, int(cfg.pass_max_offset_m / _STEP_M) + 1) * _STEP_M

    def least(sign: float) -> float | None:
        for d in sign * tried:
            if not (np.abs(lat_there - d) < clear).any():
                return float(d)
        return None

    return Blocker(g0, least(1.0), least(-1.0))


def pass_candidates(path, speed: float, aim: float, scene: ForecastScene, cfg, steps: int,
                    dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """IDM runs along ``path`` shifted past the parked blocker on either side.

    Args:
        path: the plan's :class:`~renderworld.planning.path.PlanPath`.
        speed: the ego's speed now, m/s.
        aim: the speed the IDM runs aim at (their targets: ``cfg.speed_fractions`` of it), m/s.
        scene: the forecast scene (the blocker, the IDM leaders along the shifted paths).
        cfg: the :class:`~renderworld.planning.candidates.CheckConfig`.
        steps: waypoints per candidate.
        dt: seconds between waypoints.

    Returns:
        (waypoints [N, steps, 2] metres, offsets [N] metres, target speeds [N] m/s): N = 0
        when no parked road user blocks the path or ``cfg.pass_parked`` is off; else, per side
        whose offset lies within ``cfg.pass_max_offset_m``, one run per speed fraction.
    """
    blocker = parked_blocker(scene, path, speed, cfg) if cfg.pass_parked else None
    sides = [] if blocker is None else [d for d in (blocker.left, blocker.right) if d is not None]
    if not sides or not cfg.speed_fractions:
        return np.zeros((0, steps, 2)), np.zeros(0), np.zeros(0)
    ramp = max(cfg.ramp_m, cfg.pass_ramp_s * speed)
    ramp = min(ramp, max(blocker.gap_m - 1.0, 6.0))  # beside it before reaching it
    pcfg = replace(cfg, ramp_m=ramp, quintic_ramp=True)
    targets = [fr * aim for fr in cfg.speed_fractions]
    wps, offs, spd = [], [], []
    for d, lead in zip(sides, leaders(scene, path, tuple(sides), pcfg, steps * dt)):
        arcs = idm_arc(speed, targets, lead, pcfg, steps, dt)
        wps.append(path.offset(arcs, d, ramp, quintic=True))
        offs += [d] * len(targets)
        spd += targets
    return np.concatenate(wps), np.array(offs), np.array(spd)
