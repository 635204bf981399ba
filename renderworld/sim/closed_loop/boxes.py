"""Oriented boxes of the ego and of every object of a world, and the checks made on them.

Boxes are ground footprints in the scene frame: centre (m), yaw (rad, of the length axis) and
half (length, width) (m). The ego box is ``EGO_LENGTH`` x ``EGO_WIDTH`` centred
``EGO_CENTRE_OFFSET`` ahead of the rear axle (the simulator's own ego box,
:func:`renderworld.sim.layout.ego_box_at`); an object's is
:meth:`renderworld.sim.objects.SimObject.footprint_half` at its trajectory's pose. Overlaps use
the simulator's separating-axis test (:func:`renderworld.sim.agents.rects_overlap`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import EGO_LENGTH, EGO_WIDTH
from renderworld.sim.agents import rects_overlap
from renderworld.sim.layout import World, ego_box_at
from renderworld.sim.roads import ROAD

__all__ = ["EGO_HALF", "SceneBoxes", "Contact", "ego_on_road", "first_contact"]

EGO_HALF = np.array([EGO_LENGTH / 2, EGO_WIDTH / 2])
_VEL_DT = 0.05  # seconds either side for an object's velocity


@dataclass(frozen=True)
class Contact:
    """An overlap of the ego box with an object's box.

    Attributes:
        key: the object's key (e.g. ``scn_lead``).
        category: its category (e.g. ``vehicle.car``).
        at_fault: False when the object touches the ego from behind (its centre behind the
            ego's rear bumper along the ego heading): a car standing or slower than the one
            behind is not to blame. Standing in someone's way elsewhere (e.g. stopped inside
            the oncoming lane) is at fault.
    """

    key: str
    category: str
    at_fault: bool


class SceneBoxes:
    """Every object's box at any time; static ones computed once.

    Args:
        world: the generated scene.
    """

    def __init__(self, world: World):
        objs = list(world.objects)
        self.keys = [o.key for o in objs]
        self.categories = [o.category for o in objs]
        self.half = np.array([o.footprint_half() for o in objs]).reshape(-1, 2)
        self.moving = np.array([bool(o.moving) for o in objs], dtype=bool)
        self._objs = objs
        self._static_c = np.array([o.trajectory.xy[0] for o in objs]).reshape(-1, 2)
        self._static_y = np.array([o.trajectory.yaw[0] for o in objs]).reshape(-1)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(centres [M, 2], yaws [M]) at time ``t`` seconds."""
        c, y = self._static_c.copy(), self._static_y.copy()
        for i in np.flatnonzero(self.moving):
            xy, yaw = self._objs[i].trajectory.pose(t)
            c[i], y[i] = xy, yaw
        return c, y

    def velocity(self, t: float) -> np.ndarray:
        """[M, 2] m/s, scene frame (finite difference over 0.1 s; 0 for static objects)."""
        v = np.zeros((len(self.keys), 2))
        for i in np.flatnonzero(self.moving):
            a, _ = self._objs[i].trajectory.pose(t - _VEL_DT)
            b, _ = self._objs[i].trajectory.pose(t + _VEL_DT)
            v[i] = (b - a) / (2 * _VEL_DT)
        return v


def first_contact(boxes: SceneBoxes, t: float, x: float, y: float, yaw: float):
    """The first object (in world order) whose box overlaps the ego box, or None."""
    ec, ey = ego_box_at(np.array([x, y]), yaw)
    c, yy = boxes.at(t)
    near = np.hypot(*(c - ec).T) < np.hypot(*EGO_HALF) + np.hypot(*boxes.half.T) + 0.1
    if not near.any():
        return None
    idx = np.flatnonzero(near)
    hit = rects_overlap(ec, ey, EGO_HALF, c[idx], yy[idx], boxes.half[idx])
    if not hit.any():
        return None
    i = int(idx[np.argmax(hit)])
    rel = c[i] - ec
    along = float(np.cos(yaw) * rel[0] + np.sin(yaw) * rel[1])
    behind = along < -EGO_HALF[0]
    return Contact(boxes.keys[i], boxes.categories[i], not behind)


def ego_on_road(world: World, x: float, y: float, yaw: float) -> bool:
    """Whether the ego box's corners and edge midpoints all lie on the driveable surface."""
    ec, _ = ego_box_at(np.array([x, y]), yaw)
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-np.sin(yaw), np.cos(yaw)])
    g = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1], [1, 0], [-1, 0], [0, 1], [0, -1]])
    pts = ec + (g[:, :1] * EGO_HALF[0]) * u + (g[:, 1:] * EGO_HALF[1]) * v
    return bool((world.raster.classify(pts) == ROAD).all())
