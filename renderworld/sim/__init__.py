"""Driving-scene simulator writing nuScenes-format datasets with lidarseg and Occ3D labels.

Scene descriptions (:mod:`renderworld.sim.scene`) → procedural worlds (roads, buildings,
vegetation, props, parked and moving vehicles, pedestrians, an ego route) → Open3D ray-cast
LiDAR and cameras → Occ3D ground truth → the nuScenes on-disk layout. Open3D is imported only
when ray casting starts, so ``import renderworld.sim`` stays light.
"""

from renderworld.sim.effects import EFFECTS, EffectReport
from renderworld.sim.scene import (
    BEHAVIOURS,
    INTERACTIONS,
    OBJECT_CATEGORIES,
    ROAD_KINDS,
    WEATHERS,
    EffectsSpec,
    ObjectSpec,
    SceneSpec,
    SensorSpec,
    SimConfig,
)
from renderworld.sim.simulate import REPORT_NAME, build_worlds, ego_pose_matrix, simulate
from renderworld.sim.traffic import build_world

__all__ = [
    "BEHAVIOURS",
    "EFFECTS",
    "INTERACTIONS",
    "OBJECT_CATEGORIES",
    "REPORT_NAME",
    "ROAD_KINDS",
    "WEATHERS",
    "EffectReport",
    "EffectsSpec",
    "ObjectSpec",
    "SceneSpec",
    "SensorSpec",
    "SimConfig",
    "build_world",
    "build_worlds",
    "ego_pose_matrix",
    "simulate",
]
