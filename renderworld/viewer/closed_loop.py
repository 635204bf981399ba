"""A Rerun recording of closed-loop episodes of one scene (``tools/drive.py record=<scene>``).

Entity layout (scene frame, metres, z up; timeline ``sim_time``, seconds, 10 Hz)::

    world                         Occ3D class names/colours (static)
    world/logged_path             the logged ego's rear-axle path (static)
    world/agents                  every moving object's box and the static ones near the route,
                                  coloured by Occ3D class
    world/<planner>/ego           the ego box (white), at the ego's actual pose
    world/<planner>/path          the path driven so far
    world/<planner>/collision     where the episode ended in a collision (red point)

Open with ``rerun <file>.rrd``.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np

from renderworld.constants import LIDARSEG_TO_OCC3D
from renderworld.sim.closed_loop.boxes import EGO_HALF, SceneBoxes
from renderworld.sim.layout import World, ego_box_at
from renderworld.viewer._rerun import class_annotations, require_rerun

__all__ = ["write_episode_recording"]

_EGO_HEIGHT = 1.6
_COLOURS = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
]


def _quats(yaw: np.ndarray) -> np.ndarray:
    q = np.zeros((len(yaw), 4), dtype=np.float32)  # x, y, z, w: a rotation about z
    q[:, 2], q[:, 3] = np.sin(yaw / 2), np.cos(yaw / 2)
    return q


def write_episode_recording(world: World, episodes: list, out) -> Path:
    """Write the episodes (one per planner) of ``world`` as a Rerun recording.

    Args:
        world: the scene driven.
        episodes: :class:`renderworld.sim.closed_loop.Episode` s of that scene.
        out: the ``.rrd`` file to write (written to a temporary file, then renamed).

    Raises:
        ImportError: rerun-sdk is not installed (the message says how to install it).
        ValueError: no episode, or an episode of another scene.
    """
    rr = require_rerun()
    if not episodes:
        raise ValueError("episodes: expected at least one episode, got none")
    for e in episodes:
        if e.scene != world.name:
            raise ValueError(f"episodes: expected scene {world.name}, got one of {e.scene}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    boxes = SceneBoxes(world)
    objs = world.objects
    cls = np.array([LIDARSEG_TO_OCC3D[o.label] for o in objs], dtype=np.uint16)
    height = np.array([o.size[2] for o in objs], dtype=np.float32)
    route_xy = np.concatenate([e.states[:, :2] for e in episodes])
    reach = np.hypot(*(boxes.at(0.0)[0][:, None, :] - route_xy[None, ::10]).transpose(2, 0, 1))
    shown = boxes.moving | ((reach.min(1) < 40.0) & (boxes.half.max(1) < 6.0))
    tmp = out.parent / f".{out.name}.{uuid.uuid4().hex[:8]}.tmp.rrd"
    rec = rr.RecordingStream("renderworld", recording_id=f"{world.name}-{uuid.uuid4().hex[:8]}")
    try:
        rec.save(tmp)
        rec.log("/", rr.TextDocument(f"RenderWorld closed loop: {world.name}"), static=True)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world", class_annotations(rr), static=True)
        log_xy = world.ego.trajectory.pose(np.arange(0.0, world.duration + 1e-9, 0.1))[0]
        pts = np.c_[log_xy, np.full(len(log_xy), 0.05)].astype(np.float32)
        rec.log(
            "world/logged_path",
            rr.LineStrips3D([pts], colors=[(0, 0, 0)], radii=[0.08], labels=["logged ego"]),
            static=True,
        )
        times = np.unique(np.concatenate([e.times for e in episodes]))
        for t in times:
            rec.set_time("sim_time", duration=float(t))
            c, yaw = boxes.at(float(t))
            rec.log(
                "world/agents",
                rr.Boxes3D(
                    centers=np.c_[c[shown], height[shown] / 2].astype(np.float32),
                    half_sizes=np.c_[boxes.half[shown], height[shown] / 2].astype(np.float32),
                    quaternions=_quats(yaw[shown]),
                    class_ids=cls[shown],
                    show_labels=False,
                ),
            )
            for n, e in enumerate(episodes):
                k = int(np.searchsorted(e.times, t + 1e-9)) - 1
                if k < 0 or t > e.times[-1] + 1e-9:
                    continue
                x, y, h, _ = e.states[k]
                ec, ey = ego_box_at(np.array([x, y]), h)
                colour = _COLOURS[n % len(_COLOURS)]
                rec.log(
                    f"world/{e.planner}/ego",
                    rr.Boxes3D(
                        centers=[[*ec, _EGO_HEIGHT / 2]],
                        half_sizes=[[*EGO_HALF, _EGO_HEIGHT / 2]],
                        quaternions=_quats(np.array([ey])),
                        colors=[colour],
                        labels=[e.planner],
                    ),
                )
                path = np.c_[e.states[: k + 1, :2], np.full(k + 1, 0.1)].astype(np.float32)
                rec.log(
                    f"world/{e.planner}/path", rr.LineStrips3D([path], colors=[colour], radii=[0.1])
                )
                if e.end == "collision" and k == len(e.times) - 1:
                    rec.log(
                        f"world/{e.planner}/collision",
                        rr.Points3D(
                            [[x, y, 1.0]],
                            colors=[(255, 0, 0)],
                            radii=[0.6],
                            labels=[f"collision: {e.contact.key}"],
                        ),
                    )
        rec.flush()
        rec.disconnect()
        os.replace(tmp, out)
    except BaseException:
        rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise
    return out
