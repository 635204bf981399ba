"""Simulated objects: solid primitives per category, their classes, colours and motion.

An object is a set of primitives (boxes, vertical cylinders, spheres, cones) in the object
frame (x along the object's length, y left, z up from the ground) plus a trajectory. The same
primitives are triangulated for ray casting (:mod:`renderworld.sim.meshes`) and voxelised
analytically for Occ3D (:mod:`renderworld.sim.occupancy`); each mesh lies inside its analytic
solid, so every LiDAR hit falls in a voxel the voxeliser marks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.constants import LIDARSEG_CLASSES
from renderworld.sim.agents import Trajectory

__all__ = ["BOX", "CYLINDER", "SPHERE", "CONE", "SimObject", "make_object", "CLASS_COLOURS"]

BOX, CYLINDER, SPHERE, CONE = 0, 1, 2, 3

#: Base RGB colour (0..1) per lidarseg class used by the camera shader; distinct per class.
CLASS_COLOURS: dict[int, tuple[float, float, float]] = {
    2: (0.85, 0.25, 0.20),  # pedestrian: red clothing
    9: (0.92, 0.92, 0.90),  # barrier: white (red stripes in the shader)
    12: (1.00, 0.45, 0.05),  # traffic cone: orange
    14: (0.80, 0.30, 0.80),  # bicycle: magenta
    16: (0.95, 0.80, 0.10),  # bus: yellow
    17: (0.20, 0.35, 0.75),  # car: blue
    18: (0.95, 0.60, 0.05),  # construction vehicle: amber
    21: (0.55, 0.10, 0.15),  # motorcycle: dark red
    22: (0.45, 0.30, 0.20),  # trailer: brown
    23: (0.90, 0.90, 0.85),  # truck: white
    24: (0.30, 0.30, 0.32),  # driveable surface: asphalt
    26: (0.70, 0.68, 0.62),  # sidewalk: light paving
    27: (0.45, 0.55, 0.25),  # terrain: grass and soil
    28: (0.72, 0.62, 0.50),  # manmade: facades
    30: (0.15, 0.45, 0.15),  # vegetation: green
}


@dataclass
class SimObject:
    """One object of a scene.

    Attributes:
        key: unique name within the scene (token seeds).
        category: lidarseg class name.
        label: lidarseg index of every primitive.
        size: (width, length, height) metres, the annotation box.
        shape: [P] primitive shape codes (BOX, CYLINDER, SPHERE, CONE).
        centre: [P, 3] primitive centres, object frame, metres (cones: base centre).
        dims: [P, 3] (length, width, height) of boxes; (2r, 2r, h) of cylinders and cones;
            (2r, 2r, 2r) of spheres; metres.
        yaw: [P] primitive yaw in the object frame, radians.
        part: [P] shading part (0 body, 1 glass, 2 trunk, 3 stripes).
        colour: RGB 0..1, the instance's colour.
        trajectory: ground pose over time (static objects have a fixed one).
        moving: whether the object moves (agent-motion effect).
        annotate: whether the object gets sample_annotation boxes.
    """

    key: str
    category: str
    label: int
    size: tuple[float, float, float]
    shape: np.ndarray
    centre: np.ndarray
    dims: np.ndarray
    yaw: np.ndarray
    part: np.ndarray
    colour: tuple[float, float, float]
    trajectory: Trajectory
    moving: bool = False
    annotate: bool = True

    def footprint_half(self) -> np.ndarray:
        """[2] half (length, width) of the ground footprint, metres (a tree's is its trunk)."""
        if self.label == 30 and self.shape[0] == CYLINDER:
            return np.array([0.3, 0.3])
        return np.array([self.size[1] / 2, self.size[0] / 2])


def _prims(rows: list[tuple]) -> dict[str, np.ndarray]:
    return {
        "shape": np.array([r[0] for r in rows], dtype=np.int64),
        "centre": np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 3),
        "dims": np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 3),
        "yaw": np.array([r[3] if len(r) > 3 else 0.0 for r in rows], dtype=np.float64),
        "part": np.array([r[4] if len(r) > 4 else 0 for r in rows], dtype=np.int64),
    }


def _box(cx, cz, length, width, z0, z1, part=0, cy=0.0):
    return (BOX, (cx, cy, (z0 + z1) / 2), (length, width, z1 - z0), 0.0, part)


def _vehicle(category: str, w: float, ln: float, h: float) -> list[tuple]:
    if category == "vehicle.car":
        return [
            _box(0.0, 0, ln, w, 0.3, 0.55 * h + 0.1),
            _box(-0.08 * ln, 0, 0.55 * ln, 0.92 * w, 0.55 * h + 0.1, h, part=1),
        ]
    if category == "vehicle.truck":
        return [
            _box(0.38 * ln, 0, 0.22 * ln, w, 0.4, 0.8 * h, part=1),
            _box(-0.12 * ln, 0, 0.74 * ln, w, 0.5, h),
        ]
    if category in ("vehicle.bus.rigid", "vehicle.bus.bendy"):
        return [_box(0.0, 0, ln, w, 0.3, 0.45 * h), _box(0.0, 0, ln, w, 0.45 * h, h, part=1)]
    if category == "vehicle.trailer":
        return [_box(0.0, 0, ln, w, 1.0, h)]
    if category == "vehicle.construction":
        return [
            _box(-0.1 * ln, 0, 0.8 * ln, w, 0.4, 0.55 * h),
            _box(-0.25 * ln, 0, 0.35 * ln, 0.8 * w, 0.55 * h, h, part=1),
            _box(0.35 * ln, 0, 0.3 * ln, 0.3 * w, 0.55 * h, 0.8 * h),
        ]
    # two-wheelers: frame plus rider
    return [
        _box(0.0, 0, ln, w, 0.25, 0.95),
        (CYLINDER, (-0.1 * ln, 0.0, (0.95 + h) / 2), (0.45, 0.45, h - 0.95), 0.0, 1),
    ]


def make_object(
    key: str,
    category: str,
    size: tuple[float, float, float],
    trajectory: Trajectory,
    rng: np.random.Generator,
    moving: bool = False,
    variant: str = "",
) -> SimObject:
    """Build an object of a lidarseg ``category`` with annotation ``size`` (width, length, height).

    Args:
        key: unique name within the scene.
        category: lidarseg class name (see ``scene.OBJECT_CATEGORIES``).
        size: (width, length, height) metres.
        trajectory: its ground pose over time.
        rng: randomness for colour jitter.
        moving: whether it moves.
        variant: ``"hedge"`` turns vegetation into a hedge instead of a tree.
    """
    w, ln, h = (float(v) for v in size)
    label = LIDARSEG_CLASSES.index(category)
    annotate = True
    if category.startswith("vehicle."):
        rows = _vehicle(category, w, ln, h)
    elif category.startswith("human."):
        rows = [
            (CYLINDER, (0, 0, 0.75 * h / 2), (0.75 * w, 0.75 * w, 0.75 * h), 0.0, 0),
            (CYLINDER, (0, 0, 0.75 * h + 0.1 * h), (0.7 * w, 0.7 * w, 0.2 * h), 0.0, 1),
            (SPHERE, (0, 0, 0.9 * h), (0.35 * w, 0.35 * w, 0.35 * w), 0.0, 2),
        ]
    elif category == "movable_object.barrier":
        rows = [_box(0.0, 0, ln, w, 0.0, h, part=3)]
    elif category == "movable_object.trafficcone":
        rows = [(CONE, (0, 0, 0.0), (w, w, h), 0.0, 3)]
    elif category == "static.manmade":
        rows = [_box(0.0, 0, ln, w, 0.0, h)]
        annotate = False
    elif category == "static.vegetation":
        annotate = False
        if variant == "hedge":
            rows = [_box(0.0, 0, ln, w, 0.0, h)]
        else:
            r = min(w, ln) / 2
            trunk = max(h - 2 * r, 1.0)
            rows = [
                (CYLINDER, (0, 0, trunk / 2), (0.35, 0.35, trunk), 0.0, 2),
                (SPHERE, (0, 0, min(trunk + r * 0.85, h - r)), (2 * r, 2 * r, 2 * r), 0.0, 0),
            ]
    else:
        raise ValueError(f"category: class {category!r} is not simulated")
    base = np.asarray(CLASS_COLOURS.get(label, (0.5, 0.5, 0.5)))
    colour = np.clip(base * rng.uniform(0.8, 1.15) + rng.normal(0, 0.04, 3), 0.02, 1.0)
    return SimObject(
        key=key,
        category=category,
        label=label,
        size=(w, ln, h),
        colour=tuple(float(c) for c in colour),
        trajectory=trajectory,
        moving=moving,
        annotate=annotate,
        **_prims(rows),
    )
