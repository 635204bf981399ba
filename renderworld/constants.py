"""Constants shared by every RenderWorld module.

Class lists and maps, grid specifications, sensor names and the keyframe time step live
here and only here (docs/conventions.md#layout). Nothing in this module imports from the package.

Frames and conventions: occupancy grids are indexed ``[x, y, z]`` in the ego frame
(x forward, y left, z up, metres); voxel centre = ``min + (i + 0.5) * size``.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "IGNORE_LABEL",
    "SIM_VERSION",
    "REPORTED_CHECKPOINT",
    "OCC3D_CLASSES",
    "NUM_OCC3D_CLASSES",
    "NUM_SEMANTIC_CLASSES",
    "FREE_ID",
    "OTHERS_ID",
    "OBJECT_CLASS_IDS",
    "MOVABLE_CLASS_IDS",
    "VULNERABLE_CLASS_IDS",
    "OCC3D_COLORS",
    "LIDARSEG_CLASSES",
    "LIDARSEG_TO_OCC3D",
    "lidarseg_to_occ3d_lut",
    "CAMERA_NAMES",
    "LIDAR_NAME",
    "GridSpec",
    "OCC3D_RANGE",
    "OCC3D_GRID",
    "GRIDS",
    "get_grid",
    "KEYFRAME_DT",
    "HISTORY_FRAMES",
    "FUTURE_FRAMES",
    "COMMANDS",
    "COMMAND_LATERAL_THRESHOLD",
    "EGO_CENTRE_OFFSET",
    "EGO_LENGTH",
    "EGO_WIDTH",
    "MINI_TRAIN_SCENES",
    "MINI_VAL_SCENES",
    "NUSCENES_TABLES",
]

# --------------------------------------------------------------------------------------
# Occ3D-nuScenes classes (18): 0..16 semantic, 17 free ("air").
# --------------------------------------------------------------------------------------
OCC3D_CLASSES: tuple[str, ...] = (
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)
NUM_OCC3D_CLASSES: int = len(OCC3D_CLASSES)  # 18, free included
NUM_SEMANTIC_CLASSES: int = NUM_OCC3D_CLASSES - 1  # 17, the non-air classes 0..16
FREE_ID: int = OCC3D_CLASSES.index("free")  # 17
OTHERS_ID: int = OCC3D_CLASSES.index("others")  # 0
#: 2-D label of pixels without a LiDAR point, and of points without semantics (depth-only sweeps).
IGNORE_LABEL: int = 255
#: Object classes used by the occupancy collision metric (barrier .. truck).
OBJECT_CLASS_IDS: tuple[int, ...] = tuple(range(1, 11))
#: Classes of road users that can move (car, truck, bus, trailer, construction_vehicle,
#: pedestrian, bicycle, motorcycle): the "movers" of the forecast metrics and baselines.
MOVABLE_CLASS_IDS: tuple[int, ...] = tuple(
    sorted(
        OCC3D_CLASSES.index(c)
        for c in (
            "car",
            "truck",
            "bus",
            "trailer",
            "construction_vehicle",
            "pedestrian",
            "bicycle",
            "motorcycle",
        )  # fmt: skip
    )
)
#: Vulnerable road users (pedestrian, bicycle, motorcycle): the planner keeps a wider berth.
VULNERABLE_CLASS_IDS: tuple[int, ...] = tuple(
    OCC3D_CLASSES.index(c) for c in ("pedestrian", "bicycle", "motorcycle")
)

#: RGB colours (uint8) per Occ3D class, in class order; free is white.
OCC3D_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # others
    (255, 120, 50),  # barrier
    (255, 192, 203),  # bicycle
    (255, 255, 0),  # bus
    (0, 150, 245),  # car
    (0, 255, 255),  # construction_vehicle
    (200, 180, 0),  # motorcycle
    (255, 0, 0),  # pedestrian
    (255, 240, 150),  # traffic_cone
    (135, 60, 0),  # trailer
    (160, 32, 240),  # truck
    (255, 0, 255),  # driveable_surface
    (139, 137, 137),  # other_flat
    (75, 0, 75),  # sidewalk
    (150, 240, 80),  # terrain
    (230, 230, 250),  # manmade
    (0, 175, 0),  # vegetation
    (255, 255, 255),  # free
)

# --------------------------------------------------------------------------------------
# nuScenes lidarseg (32 classes, official index order) and its map to Occ3D.
# --------------------------------------------------------------------------------------
LIDARSEG_CLASSES: tuple[str, ...] = (
    "noise",
    "animal",
    "human.pedestrian.adult",
    "human.pedestrian.child",
    "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer",
    "human.pedestrian.stroller",
    "human.pedestrian.wheelchair",
    "movable_object.barrier",
    "movable_object.debris",
    "movable_object.pushable_pullable",
    "movable_object.trafficcone",
    "static_object.bicycle_rack",
    "vehicle.bicycle",
    "vehicle.bus.bendy",
    "vehicle.bus.rigid",
    "vehicle.car",
    "vehicle.construction",
    "vehicle.emergency.ambulance",
    "vehicle.emergency.police",
    "vehicle.motorcycle",
    "vehicle.trailer",
    "vehicle.truck",
    "flat.driveable_surface",
    "flat.other",
    "flat.sidewalk",
    "flat.terrain",
    "static.manmade",
    "static.other",
    "static.vegetation",
    "vehicle.ego",
)

#: lidarseg index -> Occ3D class id (docs/conventions.md#from-lidarseg-to-occ3d). Every one of the
#: 32 indices is present.
LIDARSEG_TO_OCC3D: dict[int, int] = {
    0: 0, 1: 0, 2: 7, 3: 7, 4: 7, 5: 0, 6: 7, 7: 0, 8: 0, 9: 1, 10: 0, 11: 0, 12: 8,
    13: 0, 14: 2, 15: 3, 16: 3, 17: 4, 18: 5, 19: 0, 20: 0, 21: 6, 22: 9, 23: 10,
    24: 11, 25: 12, 26: 13, 27: 14, 28: 15, 29: 0, 30: 16, 31: 0,
}  # fmt: skip


def lidarseg_to_occ3d_lut() -> list[int]:
    """Return a 256-entry lookup table from a uint8 lidarseg label to its Occ3D id.

    Labels outside 0..31 map to ``OTHERS_ID``; callers that need to reject them check first.

    Returns:
        list[int] of length 256.
    """
    lut = [OTHERS_ID] * 256
    for src, dst in LIDARSEG_TO_OCC3D.items():
        lut[src] = dst
    return lut


# --------------------------------------------------------------------------------------
# Sensors
# --------------------------------------------------------------------------------------
#: The six nuScenes cameras, in the order converters and models use.
CAMERA_NAMES: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
LIDAR_NAME: str = "LIDAR_TOP"

#: The 13 required nuScenes tables (``<version>/<name>.json``).
NUSCENES_TABLES: tuple[str, ...] = (
    "category",
    "attribute",
    "visibility",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "map",
)

#: Official v1.0-mini split.
MINI_TRAIN_SCENES: tuple[str, ...] = (
    "scene-0061",
    "scene-0553",
    "scene-0655",
    "scene-0757",
    "scene-0796",
    "scene-1077",
    "scene-1094",
    "scene-1100",
)
MINI_VAL_SCENES: tuple[str, ...] = ("scene-0103", "scene-0916")


# --------------------------------------------------------------------------------------
# Grids
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GridSpec:
    """An axis-aligned voxel grid in the ego frame.

    Attributes:
        name: Short identifier used in configs (e.g. ``"occ3d"``).
        range_min: (x, y, z) lower corner in metres, ego frame.
        range_max: (x, y, z) upper corner in metres, ego frame.
        shape: (X, Y, Z) number of voxels per axis.
    """

    name: str
    range_min: tuple[float, float, float]
    range_max: tuple[float, float, float]
    shape: tuple[int, int, int]

    @property
    def voxel_size(self) -> tuple[float, float, float]:
        """Voxel edge length per axis, metres."""
        return tuple((hi - lo) / n for lo, hi, n in zip(self.range_min, self.range_max, self.shape))  # type: ignore[return-value]

    @property
    def num_voxels(self) -> int:
        """X * Y * Z."""
        x, y, z = self.shape
        return x * y * z


OCC3D_RANGE: tuple[float, ...] = (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4)
OCC3D_GRID = GridSpec("occ3d", (-40.0, -40.0, -1.0), (40.0, 40.0, 5.4), (200, 200, 16))

#: Grids of the Occ3D range; coarser ones are integer down-samplings of the Occ3D grid.
GRIDS: dict[str, GridSpec] = {
    "occ3d": OCC3D_GRID,  # 0.4 m, 200x200x16
    "half": GridSpec("half", OCC3D_GRID.range_min, OCC3D_GRID.range_max, (100, 100, 8)),  # 0.8 m
    "quarter": GridSpec("quarter", OCC3D_GRID.range_min, OCC3D_GRID.range_max, (50, 50, 8)),
    "coarse": GridSpec("coarse", OCC3D_GRID.range_min, OCC3D_GRID.range_max, (50, 50, 4)),
}


def get_grid(name: str) -> GridSpec:
    """Look up a named grid.

    Args:
        name: One of ``GRIDS``' keys.

    Raises:
        ValueError: if ``name`` is not a known grid.
    """
    if name not in GRIDS:
        raise ValueError(f"grid: unknown grid {name!r}; expected one of {sorted(GRIDS)}")
    return GRIDS[name]


# --------------------------------------------------------------------------------------
# Time, commands, ego
# --------------------------------------------------------------------------------------
KEYFRAME_DT: float = 0.5  # seconds between keyframes (2 Hz)
HISTORY_FRAMES: int = 5  # t-4 .. t
FUTURE_FRAMES: int = 6  # t+1 .. t+6 (3 s)
COMMANDS: tuple[str, ...] = ("left", "right", "straight")
COMMAND_LATERAL_THRESHOLD: float = 2.0  # metres of lateral offset at 3 s
EGO_LENGTH: float = 4.084  # metres
EGO_WIDTH: float = 1.85  # metres
#: The ego box centre lies this far ahead of the rear axle (the ego origin), metres.
EGO_CENTRE_OFFSET: float = 1.1

#: The nuScenes version folder the simulated fixtures are written as (official mini names).
SIM_VERSION: str = "v1.0-mini"

#: The checkpoint of each training run that the main job evaluates, bundles, exports and
#: reports. ``best.pt`` is chosen on the validation split by ``trainer.monitor`` (mini_val for
#: the demo), the split the report scores, so its figures would be selected on the data they
#: are reported on; the schedules are fixed step counts, so ``last.pt`` is chosen by nothing.
REPORTED_CHECKPOINT: str = "last.pt"
