"""Oriented boxes of the ego and of every object of a world, and the checks made on them.

Boxes are ground footprints in the scene frame: centre (m), yaw (rad, of the length axis) and
half (length, width) (m). The ego box is ``EGO_LENGTH`` x ``EGO_WIDTH`` centred
``EGO_CENTRE_OFFSET`` ahead of the rear axle (the simulator's own ego box,
:func:`renderworld.sim.layout.ego_box_at`); an object's is
:meth:`renderworld.sim.objects.SimObject.footprint_half` at its trajectory's pose. Overlaps use
the simulator's separating-axis test (:func:`renderworld.sim.agents.rects_overlap`); each
contact is classified and judged by :mod:`renderworld.sim.closed_loop.contacts` (NAVSIM's
at-fault rules).
"""

from __future__ import annotations

import numpy as np

from renderworld.sim.agents import rects_overlap
from renderworld.sim.closed_loop.contacts import (
    EGO_HALF,
    Contact,
    LaneMap,
    contact_at_fault,
    contact_kind,
    ego_corners,
    is_agent,
)
from renderworld.sim.layout import World, ego_box_at
from renderworld.sim.roads import ROAD

__all__ = ["EGO_HALF", "SceneBoxes", "Contact", "contacts_at", "ego_on_road", "first_contact"]

_VEL_DT = 0.05  # seconds either side for an object's velocity


class SceneBoxes:
    """Every object's box at any time; static ones computed once.

    Args:
        world: the generated scene (kept as ``world``; its lanes as ``lanes``).
    """

    def __init__(self, world: World):
        objs = list(world.objects)
        self.world = world
        self.lanes = LaneMap(world.network)
        self.keys = [o.key for o in objs]
        self.categories = [o.category for o in objs]
        self.agent = np.array([is_agent(c) for c in self.categories], dtype=bool)
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

    def overlapping(self, t: float, centre: np.ndarray, yaw: float) -> np.ndarray:
        """Indices (world order) of the objects whose box at ``t`` overlaps an ego-sized box.

        Args:
            t: seconds.
            centre: [2] the ego-sized box's centre (not the rear axle), metres.
            yaw: its heading, rad.
        """
        c, yy = self.at(t)
        near = np.hypot(*(c - centre).T) < np.hypot(*EGO_HALF) + np.hypot(*self.half.T) + 0.1
        idx = np.flatnonzero(near)
        if not len(idx):
            return idx
        return idx[rects_overlap(centre, yaw, EGO_HALF, c[idx], yy[idx], self.half[idx])]


def contacts_at(
    boxes: SceneBoxes,
    t: float,
    x: float,
    y: float,
    yaw: float,
    speed: float | None = None,
    ignore=(),
) -> list[Contact]:
    """Every object (world order, keys in ``ignore`` left out) whose box overlaps the ego's.

    Args:
        boxes: the world's boxes.
        t: seconds.
        x, y, yaw: the ego's rear axle (m) and heading (rad), scene frame.
        speed: the ego's speed, m/s (None: unknown, counted as moving).
        ignore: object keys not to report (NAVSIM ignores an object after a contact the ego was
            not at fault for).

    Returns:
        One :class:`Contact` per overlapping object, its kind and fault judged by
        :mod:`renderworld.sim.closed_loop.contacts`.
    """
    ec, _ = ego_box_at(np.array([x, y]), yaw)
    idx = [i for i in boxes.overlapping(t, ec, yaw) if boxes.keys[i] not in ignore]
    if not idx:
        return []
    c, yy = boxes.at(t)
    obj_speed = np.hypot(*boxes.velocity(t).T)
    area = None
    out = []
    for i in idx:
        kind = contact_kind((x, y, yaw), speed, c[i], float(yy[i]), boxes.half[i], obj_speed[i])
        if kind == "side" and area is None:
            area = (boxes.lanes.straddles(ego_corners(x, y, yaw)),
                    not ego_on_road(boxes.world, x, y, yaw))  # fmt: skip
        fault = contact_at_fault(kind, *(area or (False, False)))
        out.append(Contact(boxes.keys[i], boxes.categories[i], fault, kind,
                           bool(boxes.agent[i]), round(float(t), 9)))  # fmt: skip
    return out


def first_contact(boxes: SceneBoxes, t: float, x: float, y: float, yaw: float, speed=None):
    """The first object (world order) whose box overlaps the ego box (:func:`contacts_at`)."""
    hits = contacts_at(boxes, t, x, y, yaw, speed)
    return hits[0] if hits else None


def ego_on_road(world: World, x: float, y: float, yaw: float) -> bool:
    """Whether the ego box's corners and edge midpoints all lie on the driveable surface."""
    ec, _ = ego_box_at(np.array([x, y]), yaw)
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-np.sin(yaw), np.cos(yaw)])
    g = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1], [1, 0], [-1, 0], [0, 1], [0, -1]])
    pts = ec + (g[:, :1] * EGO_HALF[0]) * u + (g[:, 1:] * EGO_HALF[1]) * v
    return bool((world.raster.classify(pts) == ROAD).all())
