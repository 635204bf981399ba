"""Contacts of the ego with objects: the lanes under the ego box, the kind of contact, the fault.

The rules are NAVSIM's (``pdm_scorer``: the at-fault collision metric and ``get_collision_type``)
applied to the simulator's boxes (scene frame, metres, radians; the ego pose is its rear axle):

* **Kind** of a contact, checked in this order:

  1. ``stopped_ego``: the ego's speed is at most :data:`STOPPED_SPEED` (0.05 m/s, NAVSIM's);
  2. ``stopped_object``: the object's speed (its scripted trajectory's, 0 for a static object)
     is at most :data:`STOPPED_SPEED`;
  3. ``rear``: the object's centre, seen from the ego's rear axle, lies more than
     :data:`BEHIND_ANGLE` (150 degrees, nuPlan's ``is_agent_behind``) off the ego's heading;
  4. ``front``: the ego's front bumper (the segment between its two front corners) touches the
     object's box;
  5. ``side``: any other contact (the object touches the ego's flank).

* **At fault**: ``front`` and ``stopped_object`` always; ``side`` only when the ego straddles
  lanes (:meth:`LaneMap.straddles`) or is off the driveable surface; ``stopped_ego`` and
  ``rear`` never.
* **Agents**: objects whose category starts with ``vehicle.`` or ``human.`` (a parked car is a
  vehicle); every other category (``movable_object.*``, ``static.*``) is a static object, for
  which an at-fault contact scores NC 0.5 instead of 0 (NAVSIM: AGENT_TYPES).

Lanes (:class:`LaneMap`): a point lies in lane ``k`` of the road whose centreline is nearest
(among the roads whose carriageway holds it) when its signed offset from that centreline falls
in ``[k, k + 1)`` lane widths on its side; the parking strips and the sidewalks are in no lane.
The ego straddles lanes when its box's corners lie in two or more lanes (NAVSIM: more than one
lane polygon holds a corner and none holds all four; corners in no lane, e.g. over the parking
strip, do not count), or when a corner lies inside a junction: the simulator's junctions have
no lane connectors, every direction's paths cross there, so a flank contact inside one (e.g. a
turning ego struck by the oncoming car) is the ego's, as NAVSIM also widens its TTC test inside
intersections.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import EGO_LENGTH, EGO_WIDTH
from renderworld.sim.agents import rects_overlap
from renderworld.sim.layout import ego_box_at
from renderworld.sim.roads import RoadNetwork

__all__ = [
    "AGENT_PREFIXES",
    "AHEAD_ANGLE",
    "BEHIND_ANGLE",
    "CONTACT_KINDS",
    "EGO_HALF",
    "JUNCTION",
    "STOPPED_SPEED",
    "Contact",
    "LaneMap",
    "contact_at_fault",
    "contact_kind",
    "ego_corners",
    "is_agent",
    "relative_angle",
]

#: Half (length, width) of the ego box, metres.
EGO_HALF = np.array([EGO_LENGTH / 2, EGO_WIDTH / 2])
#: At or below this speed (m/s) the ego or an object counts as stopped (NAVSIM: 0.05).
STOPPED_SPEED = 0.05
#: An object whose centre is within this angle (rad) of the ego heading is ahead (nuPlan: 30 deg).
AHEAD_ANGLE = float(np.deg2rad(30.0))
#: An object whose centre is beyond this angle (rad) off the ego heading is behind (150 deg).
BEHIND_ANGLE = float(np.deg2rad(150.0))
#: Category prefixes of agents; every other category is a static object.
AGENT_PREFIXES = ("vehicle.", "human.")
CONTACT_KINDS = ("stopped_ego", "stopped_object", "rear", "front", "side")
#: Lane id of a point inside a junction.
JUNCTION = ("junction",)


@dataclass(frozen=True)
class Contact:
    """An overlap of the ego box with an object's box (module docstring: kind and fault).

    Attributes:
        key: the object's key (e.g. ``scn_lead``).
        category: its category (e.g. ``vehicle.car``).
        at_fault: whether the ego is to blame.
        kind: one of :data:`CONTACT_KINDS` ("" when unclassified).
        agent: whether the object is an agent (``vehicle.*``, ``human.*``) rather than a static
            object.
        t: seconds from the scene start.
    """

    key: str
    category: str
    at_fault: bool
    kind: str = ""
    agent: bool = True
    t: float = 0.0


def is_agent(category: str) -> bool:
    """Whether an object of ``category`` is an agent (vehicle or human), not a static object."""
    return category.startswith(AGENT_PREFIXES)


def ego_corners(x: float, y: float, yaw: float) -> np.ndarray:
    """[4, 2] corners of the ego box (front-left, rear-left, rear-right, front-right), metres.

    Args:
        x, y: rear axle, scene frame, metres.
        yaw: heading, radians.
    """
    c, _ = ego_box_at(np.array([x, y]), yaw)
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-np.sin(yaw), np.cos(yaw)])
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    return c + (signs[:, :1] * EGO_HALF[0]) * u + (signs[:, 1:] * EGO_HALF[1]) * v


def relative_angle(x: float, y: float, yaw: float, pts: np.ndarray) -> np.ndarray:
    """Angles [M] (rad, in [0, pi]) between the ego heading and the rear axle -> ``pts`` [M, 2].

    A point at the rear axle itself gets 0 (ahead).
    """
    rel = np.atleast_2d(np.asarray(pts, dtype=np.float64)) - np.array([x, y])
    along = rel @ np.array([np.cos(yaw), np.sin(yaw)])
    across = rel @ np.array([-np.sin(yaw), np.cos(yaw)])
    return np.abs(np.arctan2(across, along))


class LaneMap:
    """Which lane of a road network each point lies in (module docstring: the rule).

    Args:
        network: the scene's roads and junctions (:class:`renderworld.sim.roads.RoadNetwork`).
    """

    def __init__(self, network: RoadNetwork):
        self.roads = list(network.roads)
        self.junctions = list(network.junctions)
        self._segs = []
        for road in self.roads:
            pts = np.asarray(road.points, dtype=np.float64)
            seg = np.diff(pts, axis=0)
            length = np.hypot(*seg.T)
            keep = length > 1e-9
            self._segs.append((pts[:-1][keep], seg[keep], length[keep]))

    def _project(self, r: int, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance [N] to road ``r``'s centreline and signed offset [N] (left +), metres."""
        a, seg, length = self._segs[r]
        rel = pts[:, None, :] - a[None]  # [N, S, 2]
        t = np.clip((rel * seg[None]).sum(-1) / length**2, 0.0, 1.0)
        d = np.hypot(*(rel - t[..., None] * seg[None]).transpose(2, 0, 1))
        j = d.argmin(1)
        n = np.arange(len(pts))
        cross = seg[j, 0] * rel[n, j, 1] - seg[j, 1] * rel[n, j, 0]
        return d[n, j], cross / length[j]

    def lane_ids(self, pts: np.ndarray) -> list:
        """Per point [N, 2] (scene frame, metres): :data:`JUNCTION`, ``(road, lane)`` or None.

        ``lane`` counts from the centreline: 0, 1, ... on the right (the road's own direction),
        -1, -2, ... on the left; None over a parking strip, a sidewalk or off every road.
        """
        pts = np.atleast_2d(np.asarray(pts, dtype=np.float64))
        if pts.shape[-1] != 2:
            raise ValueError(f"pts: expected shape [N, 2], got {list(pts.shape)}")
        best = np.full(len(pts), np.inf)
        ids: list = [None] * len(pts)
        for r, road in enumerate(self.roads):
            if not len(self._segs[r][0]):
                continue
            d, off = self._project(r, pts)
            for i in np.flatnonzero((d <= road.half_width) & (d < best)):
                best[i] = d[i]
                k = int(np.floor(abs(off[i]) / road.lane_width))
                ids[i] = None if k >= road.lanes else (r, k if off[i] <= 0 else -(k + 1))
        for i, p in enumerate(pts):
            for j in self.junctions:
                if (abs(p[0] - j.centre[0]) <= j.half_width_y
                        and abs(p[1] - j.centre[1]) <= j.half_width_x):  # fmt: skip
                    ids[i] = JUNCTION
        return ids

    def straddles(self, corners: np.ndarray) -> bool:
        """Whether a box with ``corners`` [4, 2] lies in more than one lane or in a junction."""
        ids = self.lane_ids(corners)
        if JUNCTION in ids:
            return True
        return len({i for i in ids if i is not None}) > 1


def contact_kind(
    pose: tuple[float, float, float],
    ego_speed: float | None,
    centre: np.ndarray,
    yaw: float,
    half: np.ndarray,
    speed: float,
) -> str:
    """Kind of a contact (:data:`CONTACT_KINDS`, module docstring: the order of the checks).

    Args:
        pose: the ego's rear axle (x, y metres, yaw rad), scene frame.
        ego_speed: m/s; None when unknown (counted as moving).
        centre: [2] the object's box centre, metres.
        yaw: the object's heading, rad.
        half: [2] the object's half (length, width), metres.
        speed: the object's speed, m/s.
    """
    x, y, eyaw = pose
    if ego_speed is not None and ego_speed <= STOPPED_SPEED:
        return "stopped_ego"
    if speed <= STOPPED_SPEED:
        return "stopped_object"
    if relative_angle(x, y, eyaw, centre)[0] > BEHIND_ANGLE:
        return "rear"
    front = ego_corners(x, y, eyaw)[[0, 3]].mean(0)
    if rects_overlap(front, eyaw, np.array([0.0, EGO_HALF[1]]), centre, yaw, half):
        return "front"
    return "side"


def contact_at_fault(kind: str, straddling: bool, off_road: bool) -> bool:
    """Whether a contact of ``kind`` is the ego's fault (module docstring).

    Raises:
        ValueError: naming ``kind`` when it is not one of :data:`CONTACT_KINDS`.
    """
    if kind not in CONTACT_KINDS:
        raise ValueError(f"kind: expected one of {CONTACT_KINDS}, got {kind!r}")
    if kind in ("front", "stopped_object"):
        return True
    return kind == "side" and (straddling or off_road)
