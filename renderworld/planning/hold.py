"""The learned plan's hold-back behind leaders, relaxed where the forecast shows it safe.

:func:`~renderworld.planning.candidates.make_candidates` holds the learned plan back behind
every leader in its corridor (IDM at the plan's top speed): the headway is the margin a mover's
forecast error needs. With ``CheckConfig.hold_if_unsafe`` a plan that, as learned, meets no
forecast obstacle and keeps time to collision is driven as learned instead; with
``CheckConfig.hold_behind_movers`` it is then still held back behind the moving road users (whose
forecast may be wrong), only not behind what stands (scenery, a parked car: its forecast is
sure).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from renderworld.constants import KEYFRAME_DT
from renderworld.planning.candidates import Candidates, CheckConfig
from renderworld.planning.check import score_candidates
from renderworld.planning.idm import idm_arc, leaders
from renderworld.planning.kinematics import KinematicLimits
from renderworld.planning.scene import ForecastScene
from renderworld.planning.standing import moving_points

__all__ = ["unhold_if_safe"]


def _held_behind_movers(plan, speed, scene, path, cfg, dt) -> np.ndarray | None:
    """[S] the plan's arc lengths held back (IDM at its top speed) behind the moving road users
    only, or None where none holds it."""
    moving = moving_points(scene)
    if not moving.any():
        return None
    sub = replace(scene, points=scene.points[moving], mover=scene.mover[moving],
                  agent=scene.agent[moving], vulnerable=scene.vulnerable[moving])  # fmt: skip
    steps = len(plan)
    step = np.hypot(*np.diff(np.concatenate([np.zeros((1, 2)), plan]), axis=0).T)
    s_plan = path.arcs_of(plan)
    lead = leaders(sub, path, (0.0,), cfg, steps * dt)[0]
    if cfg.cap_coolness is not None:
        cfg = replace(cfg, acc_coolness=cfg.cap_coolness)
    held = idm_arc(speed, [max(float(step.max()) / dt, speed)], lead, cfg, steps, dt)[0]
    if (held >= s_plan - 1e-9).all():
        return None
    return np.minimum(s_plan, held)


def unhold_if_safe(
    cands: Candidates,
    plan: np.ndarray,
    speed: float,
    past: np.ndarray,
    scene: ForecastScene,
    cfg: CheckConfig,
    start: Callable[[np.ndarray], np.ndarray],
    limits: KinematicLimits | None = None,
    dt: float = KEYFRAME_DT,
    previous: np.ndarray | None = None,
) -> None:
    """Put the learned plan back in ``cands``' first place (module docstring), in place.

    Args:
        cands: the candidates, the first the learned plan held back.
        plan: [S, 2] the learned plan's positions, metres, current ego frame.
        speed: the ego's speed now, m/s.
        past: [n, 4] the ego's recent 10 Hz states (for comfort and time to collision).
        scene: the forecast scene.
        cfg: the knobs (``hold_if_unsafe``, ``hold_behind_movers``).
        start: what the check does to every candidate's waypoints [N, S, 2] before scoring (its
            start and the leader-stop cap), done to the plan too.
        limits: the kinematic model's limits.
        dt: seconds between waypoints.
        previous: the previous plan's waypoints carried on to now, or None.
    """
    raw = start(np.asarray(plan, dtype=np.float64)[None, :, :2])
    if np.allclose(raw[0], cands.waypoints[0], rtol=0.0, atol=1e-9):
        return
    one = Candidates(raw, ["plan"], np.zeros(1), cands.speed[:1], cands.reference_m, cands.path)
    s = score_candidates(one, scene, past, cfg, limits, dt, previous)
    if s.NC[0] * s.TTC[0] == 0:
        return
    if cfg.hold_behind_movers and cands.path is not None:
        s_cap = _held_behind_movers(np.asarray(plan, dtype=np.float64)[:, :2], speed, scene,
                                    cands.path, cfg, dt)  # fmt: skip
        if s_cap is not None:
            raw = start(cands.path.offset(s_cap, 0.0, cfg.ramp_m, cfg.quintic_ramp)[None])
    cands.waypoints[0] = raw[0]
