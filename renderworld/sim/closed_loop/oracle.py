"""The privileged mover forecast: each tracked mover moved along its object's true future.

A headroom reference for the checked plan (``world_model_true_movers`` in the closed loop): the
same planner, candidates and scores, with the world model's mover forecast replaced by where
the scene's objects really go. Agents are non-reactive (:mod:`renderworld.sim.closed_loop`), so
their future is known at planning time. What it reads is the world's log: it is a reference,
never a method.

Each track of the current frame (:func:`renderworld.world.tracks.track_movers`, current ego
frame) is matched to the object whose box centre lies nearest its centroid now, within
:data:`MATCH_M`; its forecast displacement is that object's true displacement at 0, dt, ... S dt,
rotated into the current ego frame. A track matched to no object keeps the model's forecast
(``fallback``). A component holding two objects follows the nearer.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import KEYFRAME_DT
from renderworld.sim.closed_loop.boxes import SceneBoxes

__all__ = ["MATCH_M", "true_mover_forecaster"]

#: Largest distance (metres) between a track's centroid and an object's box centre to match.
MATCH_M = 3.0


def true_mover_forecaster(boxes: SceneBoxes, t: float, pose, fallback):
    """The :data:`~renderworld.planning.scene.MoverForecaster` of the true future at ``t``.

    Args:
        boxes: the world's boxes (:class:`~renderworld.sim.closed_loop.boxes.SceneBoxes`).
        t: seconds, the planning time.
        pose: (x, y, yaw) the actual rear-axle pose, scene frame (the current ego frame's origin).
        fallback: the forecaster of tracks that match no object.
    """
    x, y, yaw = (float(v) for v in pose)
    rot = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])  # scene -> ego

    def movers(tracks, current, history_poses, grid, steps, dt=KEYFRAME_DT) -> np.ndarray:
        out = np.asarray(fallback(tracks, current, history_poses, grid, steps, dt), np.float64)
        out = out.reshape(len(tracks), steps + 1, 2).copy()
        if not tracks or not len(boxes.keys):
            return out
        now = (boxes.at(t)[0] - (x, y)) @ rot.T  # [N, 2] object centres, ego frame
        future = np.stack([boxes.at(t + k * dt)[0] for k in range(steps + 1)], 1)  # [N, S+1, 2]
        disp = (future - future[:, :1]) @ rot.T
        for i, tr in enumerate(tracks):
            d = np.hypot(*(now - np.asarray(tr.centroid)).T)
            j = int(np.argmin(d))
            if d[j] <= MATCH_M:
                out[i] = disp[j]
        return out

    return movers
