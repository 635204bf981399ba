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
from renderworld.planning.comfort import comfort_violations
from renderworld.sim import EffectsSpec, SceneSpec, SimConfig, build_world, simulate
from renderworld.sim.agents import Path, arc_path, rects_overlap, transition_arc
from renderworld.sim.layout import TURN_TRANSITION_M
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


@pytest.mark.parametrize("angle", [np.pi / 2, -np.pi / 2, np.deg2rad(60)])
def test_transition_keeps_the_arcs_lines_and_ramps_its_curvature(angle):
    pieces = [("line", 30.0, 0), ("arc", 9.0, angle), ("line", 40.0, 0)]
    plain, eased = Path(arc_path((0, 0), 0.0, pieces)), Path(arc_path((0, 0), 0.0, pieces, 6.0))
    np.testing.assert_allclose(eased.xy[-1], plain.xy[-1], atol=1e-6)  # same exit line and end
    np.testing.assert_allclose(eased.heading[-1], plain.heading[-1], atol=1e-6)

    def kappa(path):  # curvature, 1/m, every 0.2 m
        return np.gradient(path.heading, path.s)

    def per_metre(path):  # the largest change of curvature over 1 m
        k = kappa(path)
        return np.abs(k[5:] - k[:-5]).max()

    # the plain arc's curvature jumps to 1/9 within a metre; the eased one climbs over 6 m
    assert per_metre(plain) > 0.08 and per_metre(eased) < 0.03
    mid = np.abs(eased.heading - angle / 2) < abs(angle) / 6  # the middle third of the turn
    assert np.median(np.abs(kappa(eased)[mid])) == pytest.approx(1 / 9.0, rel=0.1)  # the radius


def test_transition_is_refused_where_it_cannot_fit():
    with pytest.raises(ValueError, match="transition"):
        transition_arc(9.0, np.pi / 2, 20.0)  # longer than the arc itself
    with pytest.raises(ValueError, match="line on both sides"):
        arc_path((0, 0), 0.0, [("arc", 9.0, 1.0), ("line", 10.0, 0)], transition=6.0)
    # a short approach gets a shorter transition instead of an error
    xy = arc_path((0, 0), 0.0, [("line", 1.0, 0), ("arc", 9.0, 1.0), ("line", 10.0, 0)], 6.0)
    assert np.isfinite(xy).all() and len(xy) > 3


@pytest.mark.parametrize("behaviour", ["turn_left", "turn_right"])
def test_logged_turns_are_within_navsim_comfort(behaviour):
    """The scripted ego steers into a turn (clothoids), as a driver does: its log meets every
    NAVSIM comfort bound. With the curvature jumping onto the arc, every logged turn failed
    the yaw-acceleration bound."""
    assert TURN_TRANSITION_M > 0
    for seed in range(3):
        spec = SceneSpec(kind="intersection", behaviour=behaviour, speed=8.0)
        plan, *_ = ego_route(spec, 24, seed, 0)
        t = np.arange(0.0, 11.5, 0.1)
        xy, yaw = plan.trajectory.pose(t)
        v = np.array([plan.trajectory.speed(x) for x in t])
        states = np.concatenate([xy, yaw[:, None], v[:, None]], 1)
        assert np.rad2deg(abs(yaw[-1] - yaw[0])) > 80  # it turned
        assert comfort_violations(states) == dict.fromkeys(comfort_violations(states), 0), seed


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
