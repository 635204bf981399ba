"""Scene descriptions: plain dataclasses, validated before anything is simulated or written.

A :class:`SimConfig` lists :class:`SceneSpec` s (one per scene: road kind, ego behaviour, how
many objects of each sort, which effects run) plus sensor settings. Configs come from Hydra
(``configs/sim``) as plain dicts via :meth:`SimConfig.from_dict`; this module never imports
Hydra. Positions are metres in the scene's local frame (x east, y north, z up); the ego starts
near the origin heading +x.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from renderworld.constants import LIDARSEG_CLASSES, MINI_TRAIN_SCENES, MINI_VAL_SCENES
from renderworld.sim.sensor_spec import SensorSpec
from renderworld.sim.sensor_spec import check_int as _check_int
from renderworld.sim.sensor_spec import spec_error as _err
from renderworld.sim.splits import match_splits, splits_json

__all__ = [
    "ROAD_KINDS",
    "BEHAVIOURS",
    "INTERACTIONS",
    "behaviour_of",
    "MIN_INTERACTION_KEYFRAMES",
    "WEATHERS",
    "SIM_MODES",
    "OBJECT_CATEGORIES",
    "EffectsSpec",
    "ObjectSpec",
    "SceneSpec",
    "SensorSpec",
    "SimConfig",
]

ROAD_KINDS: tuple[str, ...] = ("straight", "curve", "intersection", "t_junction")
BEHAVIOURS: tuple[str, ...] = (
    "cruise",
    "turn_left",
    "turn_right",
    "stop_and_go",
    "lane_change_left",
    "lane_change_right",
    "parked",
    "lead_brake",
    "cut_in",
    "ped_crossing",
    "turn_oncoming",
    "overtake_parked",
)
#: Interaction behaviours (a scripted agent the ego reacts to) and the road kinds each runs on.
INTERACTIONS: dict[str, tuple[str, ...]] = {
    "lead_brake": ("straight", "intersection"),
    "cut_in": ("straight",),
    "ped_crossing": ("straight", "intersection"),
    "turn_oncoming": ("intersection",),
    "overtake_parked": ("straight",),
}
#: Interactions need room for 5 history + 6 future keyframes around the reaction.
MIN_INTERACTION_KEYFRAMES = 16
WEATHERS: tuple[str, ...] = ("clear", "rain", "fog")


def behaviour_of(description: str) -> str:
    """The behaviour named by a simulated scene's description (``scene.json``: "Simulated
    <road kind>, <behaviour>, ..."), or "" for any other description (e.g. real nuScenes)."""
    prefix = "Simulated "
    if not isinstance(description, str) or not description.startswith(prefix):
        return ""
    parts = description[len(prefix) :].split(", ")
    name = parts[1].replace(" ", "_") if len(parts) > 1 else ""
    return name if name in BEHAVIOURS else ""


SIM_MODES: tuple[str, ...] = ("full", "occupancy")  # what a run writes (SimConfig.mode)

#: lidarseg categories the simulator can build, with a default annotation size
#: (width, length, height) in metres. Vegetation objects are trees.
OBJECT_CATEGORIES: dict[str, tuple[float, float, float]] = {
    "vehicle.car": (1.9, 4.6, 1.6),
    "vehicle.truck": (2.5, 7.5, 3.2),
    "vehicle.bus.rigid": (2.8, 11.0, 3.3),
    "vehicle.trailer": (2.5, 9.0, 3.8),
    "vehicle.construction": (2.8, 6.0, 3.0),
    "vehicle.motorcycle": (0.8, 2.1, 1.5),
    "vehicle.bicycle": (0.6, 1.7, 1.7),
    "human.pedestrian.adult": (0.6, 0.6, 1.75),
    "movable_object.barrier": (2.5, 0.5, 1.0),
    "movable_object.trafficcone": (0.4, 0.4, 0.7),
    "static.manmade": (12.0, 12.0, 10.0),
    "static.vegetation": (4.0, 4.0, 6.0),
}


@dataclass
class EffectsSpec:
    """Which effects a scene runs. An effect that is off costs nothing.

    Attributes:
        ego_motion: the ego drives its route (off: it stays at the start pose).
        agent_motion: pedestrians and vehicles move (off: every agent is static geometry).
        lidar_noise: LiDAR range noise (sigma ``lidar_range_sigma`` m) and random dropout.
        camera_noise: camera sensor noise and per-frame exposure variation.
        weather: ``"clear"``, ``"rain"`` or ``"fog"`` (attenuation in LiDAR and cameras).
        night: night lighting (dim ambient, ego headlights, street lamps).
    """

    ego_motion: bool = True
    agent_motion: bool = True
    lidar_noise: bool = True
    camera_noise: bool = True
    weather: str = "clear"
    night: bool = False

    def validate(self, where: str) -> None:
        for f in ("ego_motion", "agent_motion", "lidar_noise", "camera_noise", "night"):
            if not isinstance(getattr(self, f), bool):
                raise _err(f"{where}.effects.{f}", "a bool", getattr(self, f))
        if self.weather not in WEATHERS:
            raise _err(f"{where}.effects.weather", f"one of {WEATHERS}", self.weather)


@dataclass
class ObjectSpec:
    """An explicitly placed static object (added to the procedural ones).

    Attributes:
        category: a lidarseg class name from :data:`OBJECT_CATEGORIES`.
        x: centre x, metres, scene frame.
        y: centre y, metres, scene frame.
        yaw: heading of the object's length axis, radians.
        size: (width, length, height) metres; ``None`` takes the category default.
    """

    category: str
    x: float
    y: float
    yaw: float = 0.0
    size: tuple[float, float, float] | None = None

    def validate(self, where: str) -> None:
        if self.category not in LIDARSEG_CLASSES:
            raise ValueError(
                f"{where}.category: unknown class {self.category!r}; expected a nuScenes lidarseg "
                f"class such as {sorted(OBJECT_CATEGORIES)}"
            )
        if self.category not in OBJECT_CATEGORIES:
            raise ValueError(
                f"{where}.category: class {self.category!r} is not simulated; expected one of "
                f"{sorted(OBJECT_CATEGORIES)}"
            )
        if self.size is not None and (len(self.size) != 3 or min(self.size) <= 0):
            raise _err(f"{where}.size", "3 positive sizes (width, length, height)", self.size)

    @property
    def dims(self) -> tuple[float, float, float]:
        """(width, length, height) metres."""
        return tuple(self.size) if self.size is not None else OBJECT_CATEGORIES[self.category]


@dataclass
class SceneSpec:
    """One scene: a road-kind preset, the ego behaviour, object counts and effects.

    Attributes:
        kind: road layout, one of :data:`ROAD_KINDS`.
        behaviour: ego behaviour, one of :data:`BEHAVIOURS` (turns need a junction).
        speed: ego cruise speed, m/s.
        lanes: lanes per direction (1 or 2; lane changes need 2).
        num_parked: parked vehicles along the kerbs.
        num_moving: moving vehicles (cars, trucks, buses, motorcycles, bicycles).
        num_pedestrians: pedestrians walking on sidewalks or crossing.
        num_props: barriers and traffic cones.
        num_buildings: buildings per road side (approximate; gaps are random).
        num_trees: trees and hedges per road side (approximate).
        effects: which effects run.
        objects: extra explicitly placed static objects.
        route: explicit ego waypoints ``[[x, y], ...]`` (scene frame) replacing the preset route.
    """

    kind: str = "straight"
    behaviour: str = "cruise"
    speed: float = 8.0
    lanes: int = 2
    num_parked: int = 6
    num_moving: int = 5
    num_pedestrians: int = 6
    num_props: int = 4
    num_buildings: int = 6
    num_trees: int = 6
    effects: EffectsSpec = field(default_factory=EffectsSpec)
    objects: list[ObjectSpec] = field(default_factory=list)
    route: list[list[float]] | None = None

    def validate(self, where: str = "scene") -> None:
        """Raise ValueError naming the field when the description is not simulable."""
        if self.kind not in ROAD_KINDS:
            raise _err(f"{where}.kind", f"one of {ROAD_KINDS}", self.kind)
        if self.behaviour not in BEHAVIOURS:
            raise _err(f"{where}.behaviour", f"one of {BEHAVIOURS}", self.behaviour)
        if self.behaviour in ("turn_left", "turn_right") and self.kind not in (
            "intersection",
            "t_junction",
        ):
            raise _err(f"{where}.behaviour", "a turn only on intersection/t_junction", self.kind)
        if self.behaviour in INTERACTIONS:
            self._validate_interaction(where)
        if self.kind == "t_junction" and self.behaviour not in ("turn_left", "turn_right"):
            raise _err(
                f"{where}.behaviour", "turn_left or turn_right at a t_junction", self.behaviour
            )
        if self.lanes not in (1, 2):
            raise _err(f"{where}.lanes", "1 or 2", self.lanes)
        if self.behaviour.startswith("lane_change") and self.lanes != 2:
            raise _err(f"{where}.lanes", "2 for a lane change", self.lanes)
        if not (0.0 < float(self.speed) <= 20.0):
            raise _err(f"{where}.speed", "a speed in (0, 20] m/s", self.speed)
        for f in ("num_parked", "num_moving", "num_pedestrians", "num_props"):
            _check_int(f"{where}.{f}", getattr(self, f), 0)
        for f in ("num_buildings", "num_trees"):
            _check_int(f"{where}.{f}", getattr(self, f), 0)
        self.effects.validate(where)
        for i, obj in enumerate(self.objects):
            obj.validate(f"{where}.objects[{i}]")
        if self.route is not None:
            if len(self.route) < 2 or any(len(p) != 2 for p in self.route):
                raise _err(f"{where}.route", "at least 2 waypoints [x, y]", self.route)

    def _validate_interaction(self, where: str) -> None:
        kinds = INTERACTIONS[self.behaviour]
        if self.kind not in kinds:
            raise _err(f"{where}.kind", f"one of {kinds} for {self.behaviour}", self.kind)
        if self.behaviour in ("cut_in", "turn_oncoming") and self.lanes != 2:
            raise _err(f"{where}.lanes", f"2 for {self.behaviour}", self.lanes)
        if not (5.0 <= float(self.speed) <= 15.0):
            raise _err(f"{where}.speed", f"a speed in [5, 15] m/s for {self.behaviour}", self.speed)
        if self.route is not None:
            raise _err(f"{where}.route", f"no explicit route for {self.behaviour}", self.route)
        if not (self.effects.ego_motion and self.effects.agent_motion):
            raise _err(
                f"{where}.effects", f"ego_motion and agent_motion on for {self.behaviour}",
                {"ego_motion": self.effects.ego_motion, "agent_motion": self.effects.agent_motion},
            )  # fmt: skip


@dataclass
class SimConfig:
    """Everything a simulation run needs.

    Attributes:
        seed: master seed; same seed and config give byte-identical datasets.
        version: dataset version folder name.
        keyframes: keyframes per scene (2 Hz).
        scenes: scene descriptions; scene i gets ``scene_names[i]``.
        scene_names: names, default the official mini split (8 train + 2 val).
        sensors: sensor settings.
        splits: ``{split: [scene-name patterns]}`` (``fnmatch``, e.g. ``["scene-5*"]``) written
            as ``<version>/splits.json`` for the infos builder; every scene must match exactly
            one split. ``None`` writes none (the official mini split then applies).
        mode: ``"full"`` writes every sensor file (camera JPEGs, LiDAR ``.pcd.bin``,
            lidarseg); ``"occupancy"`` writes only what the world model reads (Occ3D labels,
            tables with ego poses and boxes, maps) and skips camera shading; its Occ3D labels,
            poses and boxes equal the full mode's (:mod:`renderworld.sim.modes`).
    """

    seed: int = 0
    version: str = "v1.0-mini"
    keyframes: int = 20
    scenes: list[SceneSpec] = field(default_factory=lambda: [SceneSpec()])
    scene_names: list[str] = field(
        default_factory=lambda: list(MINI_TRAIN_SCENES) + list(MINI_VAL_SCENES)
    )
    sensors: SensorSpec = field(default_factory=SensorSpec)
    splits: dict[str, list[str]] | None = None
    mode: str = "full"

    def validate(self) -> None:
        """Validate every field; raises ValueError naming the offending one."""
        _check_int("seed", self.seed, 0)
        if self.mode not in SIM_MODES:
            raise _err("mode", f"one of {SIM_MODES}", self.mode)
        _check_int("keyframes", self.keyframes, 1)
        if not self.scenes:
            raise _err("scenes", "at least one scene", self.scenes)
        if len(self.scene_names) < len(self.scenes):
            raise _err("scene_names", f">= {len(self.scenes)} names", self.scene_names)
        names = self.scene_names[: len(self.scenes)]
        if len(set(names)) != len(names):
            raise _err("scene_names", "unique names", names)
        if not self.version or "/" in self.version:
            raise _err("version", "a folder name like 'v1.0-mini'", self.version)
        self.sensors.validate()
        for i, s in enumerate(self.scenes):
            s.validate(f"scenes[{i}]")
            if s.behaviour in INTERACTIONS and self.keyframes < MIN_INTERACTION_KEYFRAMES:
                raise _err(
                    "keyframes", f">= {MIN_INTERACTION_KEYFRAMES} for scenes[{i}].behaviour "
                    f"{s.behaviour!r}", self.keyframes,
                )  # fmt: skip
        if self.splits is not None:
            self.split_lists()

    def split_lists(self) -> dict[str, list[str]] | None:
        """``{split: [scene names]}`` from :attr:`splits` (``None`` when unset).

        Raises:
            ValueError: naming ``splits`` when it is malformed or a scene matches no split or
                several.
        """
        if self.splits is None:
            return None
        return match_splits(self.splits, [name for name, _ in self.named_scenes])

    def splits_json(self) -> bytes:
        """``splits.json`` bytes of :meth:`split_lists`."""
        return splits_json(self.split_lists())

    @property
    def named_scenes(self) -> list[tuple[str, SceneSpec]]:
        """(name, spec) pairs in order."""
        return list(zip(self.scene_names, self.scenes))

    def to_dict(self) -> dict:
        """Plain-dict form (JSON/YAML-serialisable)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> SimConfig:
        """Build from a plain dict (e.g. ``OmegaConf.to_container(cfg)``); unknown keys raise.

        ``num_scenes`` (optional) repeats/truncates ``scenes`` to that many; ``image_size``
        (optional, ``"WxH"`` or ``[W, H]``) sets the sensor image size.
        """
        if not isinstance(d, dict):
            raise TypeError(f"config: expected a dict, got {type(d).__name__}")
        d = dict(d)
        num_scenes = d.pop("num_scenes", None)
        image_size = d.pop("image_size", None)
        _check_keys("config", d, cls)
        sensors = dict(d.pop("sensors", None) or {})
        _check_keys("sensors", sensors, SensorSpec)
        if image_size is not None:
            sensors["image_width"], sensors["image_height"] = _parse_size(image_size)
        scenes = [_scene_from_dict(s, i) for i, s in enumerate(d.pop("scenes", None) or [{}])]
        if num_scenes is not None:
            n = _check_int("num_scenes", num_scenes, 1)
            scenes = [dataclasses.replace(scenes[i % len(scenes)]) for i in range(n)]
            names = list(d.get("scene_names") or cls().scene_names)
            names += [f"scene-{9000 + i:04d}" for i in range(len(names), n)]
            d["scene_names"] = names[:n]
        cfg = cls(scenes=scenes, sensors=SensorSpec(**sensors), **d)
        cfg.validate()
        return cfg


def _check_keys(where: str, d: dict, klass) -> None:
    known = {f.name for f in dataclasses.fields(klass)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"{where}: unknown keys {unknown}; expected some of {sorted(known)}")


def _parse_size(size: Any) -> tuple[int, int]:
    if isinstance(size, str):
        parts = size.lower().split("x")
    else:
        parts = list(size)
    try:
        w, h = (int(p) for p in parts)
    except (TypeError, ValueError):
        raise _err("image_size", "'WxH' or [W, H] integers", size) from None
    if w <= 0 or h <= 0:
        raise _err("image_size", "a positive image size 'WxH'", size)
    return w, h


def _scene_from_dict(d: dict, i: int) -> SceneSpec:
    if not isinstance(d, dict):
        raise TypeError(f"scenes[{i}]: expected a dict, got {type(d).__name__}")
    d = dict(d)
    _check_keys(f"scenes[{i}]", d, SceneSpec)
    eff = dict(d.pop("effects", None) or {})
    _check_keys(f"scenes[{i}].effects", eff, EffectsSpec)
    objs = []
    for j, o in enumerate(d.pop("objects", None) or []):
        o = dict(o)
        _check_keys(f"scenes[{i}].objects[{j}]", o, ObjectSpec)
        if o.get("size") is not None:
            o["size"] = tuple(float(v) for v in o["size"])
        objs.append(ObjectSpec(**o))
    route = d.pop("route", None)
    if route is not None:
        route = [[float(v) for v in p] for p in route]
    return SceneSpec(effects=EffectsSpec(**eff), objects=objs, route=route, **d)
