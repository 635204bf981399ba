"""Ego routes give every driving command; agents never interpenetrate; effects are opt-in."""

from __future__ import annotations

import numpy as np
import pytest

from renderworld.constants import (
    COMMAND_LATERAL_THRESHOLD,
    EGO_LENGTH,
    EGO_WIDTH,
    FUTURE_FRAMES,
    KEYFRAME_DT,
)
from renderworld.sim import EffectsSpec, SceneSpec, SimConfig, build_world, simulate
from renderworld.sim.agents import rects_overlap
from renderworld.sim.traffic import ego_route
from tools.make_fixtures import config_from_preset


def commands(traj, keyframes: int) -> list[str]:
    """docs/conventions.md#ego-motion-and-the-command.

    Lateral offset of the GT pose 3 s ahead in the current ego frame.
    """
    out = []
    for k in range(keyframes - FUTURE_FRAMES):
        (xy0, yaw0), (xy1, _) = traj.pose(k * KEYFRAME_DT), traj.pose((k + 6) * KEYFRAME_DT)
        d = xy1 - xy0
        lateral = -np.sin(yaw0) * d[0] + np.cos(yaw0) * d[1]
        out.append(
            "left"
            if lateral >= COMMAND_LATERAL_THRESHOLD
            else "right"
            if lateral <= -COMMAND_LATERAL_THRESHOLD
            else "straight"
        )
    return out


def test_mini_routes_give_left_right_and_straight():
    cfg = config_from_preset("mini")
    seen = {}
    for i, (name, spec) in enumerate(cfg.named_scenes):
        plan, *_ = ego_route(spec, cfg.keyframes, cfg.seed, i)
        cmds = commands(plan.trajectory, cfg.keyframes)
        seen[name] = set(cmds)
        if spec.behaviour in ("turn_left", "lane_change_left"):
            assert "left" in cmds, (name, cmds)
        if spec.behaviour in ("turn_right", "lane_change_right"):
            assert "right" in cmds, (name, cmds)
        if spec.behaviour in ("cruise", "stop_and_go") and spec.kind == "straight":
            assert set(cmds) == {"straight"}, (name, cmds)
    assert set().union(*seen.values()) == {"left", "right", "straight"}


@pytest.mark.parametrize(
    "kind, behaviour", [("straight", "stop_and_go"), ("intersection", "turn_right")]
)
def test_ego_speed_profiles_are_plausible(kind, behaviour):
    spec = SceneSpec(kind=kind, behaviour=behaviour, speed=8.0)
    plan, *_ = ego_route(spec, 24, 0, 0)
    t = np.arange(0, 11.5, 0.1)
    xy, yaw = plan.trajectory.pose(t)
    v = np.hypot(*np.diff(xy, axis=0).T) / 0.1
    assert v.max() <= 8.0 + 1e-3
    assert np.abs(np.diff(v) / 0.1).max() < 3.0  # |longitudinal acceleration| < 3 m/s^2
    lateral = v[1:] * np.abs(np.diff(yaw[1:])) / 0.1
    assert lateral.max() < 4.0  # |lateral acceleration| < 4 m/s^2
    if behaviour == "stop_and_go":
        assert v.min() < 0.05 and v[-1] > 1.0  # it stops and goes again


@pytest.mark.parametrize("kind, behaviour", [("intersection", "turn_left"), ("straight", "cruise")])
def test_agents_never_overlap_each_other_or_the_ego(kind, behaviour):
    spec = SceneSpec(kind=kind, behaviour=behaviour, num_moving=10, num_pedestrians=10)
    world = build_world("scene-0061", spec, 16, 3, 0)
    movers = [o for o in world.objects if o.moving]
    assert len(movers) >= 10
    t = np.arange(0.0, world.duration, 0.25)
    ec, ey = world.ego_box(t)
    ego_half = np.array([EGO_LENGTH / 2, EGO_WIDTH / 2])
    for a in movers:
        ca, ya = a.trajectory.pose(t)
        assert not rects_overlap(ca, ya, a.footprint_half(), ec, ey, ego_half).any(), a.key
        for b in world.objects:
            if b is a:
                continue
            cb, yb = b.trajectory.pose(t)
            hit = rects_overlap(ca, ya, a.footprint_half(), cb, yb, b.footprint_half())
            assert not hit.any(), (a.key, b.key)


def _one_scene(effects: EffectsSpec, **kw) -> SimConfig:
    cfg = SimConfig(keyframes=2, scenes=[SceneSpec(effects=effects, **kw)], scene_names=["s-1"])
    cfg.sensors.image_width, cfg.sensors.image_height = 64, 36
    cfg.sensors.lidar_azimuth_steps = 256
    return cfg


def test_static_scene_runs_no_motion_or_weather_code(tmp_path):
    off = EffectsSpec(ego_motion=False, agent_motion=False, lidar_noise=False, camera_noise=False)
    report = simulate(_one_scene(off), tmp_path / "static", progress=False)
    ran = {k for k, v in report["effects"].items() if v["ran"]}
    assert ran == set(), ran
    assert all(v["seconds"] == 0.0 and v["calls"] == 0 for v in report["effects"].values())
    busy = EffectsSpec(weather="fog", night=True)
    report = simulate(_one_scene(busy, num_moving=6), tmp_path / "busy", progress=False)
    ran = {k for k, v in report["effects"].items() if v["ran"]}
    assert ran == {"ego_motion", "agent_motion", "lidar_noise", "camera_noise", "fog", "night"}
    assert report["effects"]["fog"]["scenes"] == ["s-1"]
    for stage in ("static_build", "lidar", "camera", "semantics", "mask_camera", "write_files"):
        assert report["stages"][stage]["calls"] > 0


def test_agent_motion_off_freezes_agents():
    spec = SceneSpec(num_moving=5, effects=EffectsSpec(agent_motion=False))
    world = build_world("s", spec, 4, 0, 0)
    assert world.objects and not any(o.moving for o in world.objects)
    from renderworld.sim.meshes import Raycaster

    caster = Raycaster(world.objects, (-500, -500, 500, 500))
    assert caster.dynamic(0.5) is None and caster.dynamic_builds == 0
