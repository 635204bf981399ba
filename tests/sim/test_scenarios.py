"""Interaction scenarios: the scripted agent never touches the ego's route, a constant-velocity
extrapolation of the ego runs into it, and the ego brakes, waits or swerves as described."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from data_converters.splits import assign_splits
from renderworld.constants import EGO_LENGTH, EGO_WIDTH, FUTURE_FRAMES, KEYFRAME_DT
from renderworld.metrics.collision import collisions_with_boxes
from renderworld.sim import SceneSpec, SimConfig, build_world, build_worlds
from renderworld.sim.agents import rects_overlap
from renderworld.sim.layout import EGO_CENTRE_OFFSET
from renderworld.sim.scene import INTERACTIONS
from tools.make_fixtures import config_from_preset

K = 22  # keyframes: 10.5 s scenes
CASES = [
    ("lead_brake", "straight", 2),
    ("lead_brake", "intersection", 1),
    ("cut_in", "straight", 2),
    ("ped_crossing", "straight", 2),
    ("ped_crossing", "intersection", 1),
    ("turn_oncoming", "intersection", 2),
    ("overtake_parked", "straight", 2),
    ("overtake_parked", "straight", 1),
]
SEEDS = (0, 1, 2)


def _world(behaviour, kind, lanes, speed, seed):
    spec = SceneSpec(kind=kind, behaviour=behaviour, speed=speed, lanes=lanes)
    world = build_world("scene-6000", spec, K, seed, 3)
    (agent,) = world.ego.scripted
    assert agent in world.objects
    return world, agent


def _agent_box(agent, t):
    xy, yaw = agent.trajectory.pose(t)
    w, ln, _ = agent.size
    return xy, yaw, np.array([ln / 2, w / 2])


def _ego_pose(world, t):
    return world.ego.trajectory.pose(t)


def _speeds(world, t):
    return np.array([world.ego.trajectory.speed(x) for x in t])


def _cv_hits_sat(world, agent, k) -> bool:
    """CV oracle: last 0.5 s displacement repeated 6 times, box centred at the rear axle."""
    t = k * KEYFRAME_DT
    (p0, _), (p1, yaw) = _ego_pose(world, t - KEYFRAME_DT), _ego_pose(world, t)
    d = p1 - p0
    hd = np.arctan2(d[1], d[0]) if np.hypot(*d) >= 0.05 else yaw
    for j in range(1, FUTURE_FRAMES + 1):
        ac, ay, ah = _agent_box(agent, t + j * KEYFRAME_DT)
        if rects_overlap(p1 + j * d, hd, [EGO_LENGTH / 2, EGO_WIDTH / 2], ac, ay, ah):
            return True
    return False


def _metric_collides(world, agent, k, future_xy) -> bool:
    """The planning collision metric on ``future_xy`` [6, 2] (scene frame) vs the agent box."""
    (p, yaw) = _ego_pose(world, k * KEYFRAME_DT)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, s], [-s, c]])
    traj = (future_xy - p) @ rot.T
    boxes = []
    for j in range(1, FUTURE_FRAMES + 1):
        ac, ay, ah = _agent_box(agent, (k + j) * KEYFRAME_DT)
        q = rot @ (ac - p)
        boxes.append([[q[0], q[1], 2 * ah[0], 2 * ah[1], ay - yaw]])
    collides, evaluable = collisions_with_boxes(traj, np.array(boxes))
    assert evaluable.all()
    return bool(collides.any())


def _cv_future(world, k):
    t = k * KEYFRAME_DT
    (p0, _), (p1, _) = _ego_pose(world, t - KEYFRAME_DT), _ego_pose(world, t)
    return p1 + np.arange(1, FUTURE_FRAMES + 1)[:, None] * (p1 - p0)


@pytest.mark.parametrize("behaviour, kind, lanes", CASES)
@pytest.mark.parametrize("speed", [5.0, 12.5])  # 5 m/s: the slowest allowed, shortest CV
def test_agent_clear_of_ego_route_but_in_the_cv_path(behaviour, kind, lanes, speed):
    for seed in SEEDS:
        world, agent = _world(behaviour, kind, lanes, speed, seed)
        # (a) never overlaps the ego's actual box (scene + the 3 s after), 0.1 s steps.
        t = np.arange(0.0, world.duration + 3.0, 0.1)
        ec, ey = world.ego_box(t)
        ac, ay = agent.trajectory.pose(t)
        half = agent.footprint_half() + 0.1
        assert not rects_overlap(ac, ay, half, ec, ey, [EGO_LENGTH / 2, EGO_WIDTH / 2]).any()
        # ... nor any other object of the world (random traffic is placed around it).
        for obj in world.objects:
            if obj is not agent:
                oc, oy = obj.trajectory.pose(t)
                hit = rects_overlap(ac, ay, agent.footprint_half(), oc, oy, obj.footprint_half())
                assert not hit.any(), (seed, obj.key)
        # (b) from some keyframe with full history and future, CV runs into the agent, both by
        # box overlap and by the planning collision metric; the true future does not.
        ks = range(4, K - FUTURE_FRAMES)
        hits = [k for k in ks if _cv_hits_sat(world, agent, k)]
        assert hits, (behaviour, speed, seed)
        metric = [k for k in ks if _metric_collides(world, agent, k, _cv_future(world, k))]
        assert metric, (behaviour, speed, seed, hits)
        for k in ks:
            gt = _ego_pose(world, (k + np.arange(1, FUTURE_FRAMES + 1)) * KEYFRAME_DT)[0]
            assert not _metric_collides(world, agent, k, gt), (behaviour, speed, seed, k)


def _standing(v, t, below=0.2):
    """Longest stretch (seconds) with speed below ``below``."""
    run, best = 0.0, 0.0
    dt = t[1] - t[0]
    for x in v:
        run = run + dt if x < below else 0.0
        best = max(best, run)
    return best


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("speed", [6.5, 12.0])
def test_ego_reacts_as_described(seed, speed):
    t = np.arange(0.0, K * KEYFRAME_DT + 3.0, 0.1)
    # lead_brake: the ego stops 1.5-5 m (bumper to bumper) behind the stopped lead.
    world, lead = _world("lead_brake", "straight", 2, speed, seed)
    v = _speeds(world, t)
    assert v[0] == pytest.approx(speed, abs=0.1) and _standing(v, t) >= 1.0
    i = int(np.argmin(v))
    xy, _ = _ego_pose(world, t[i])
    gap = lead.trajectory.pose(t[i])[0][0] - lead.size[1] / 2 - (xy[0] + EGO_CENTRE_OFFSET + 2.042)
    assert 1.5 <= gap <= 5.0 and lead.trajectory.speed(t[i]) < 0.2
    # cut_in: the car moves from the next lane into the ego lane ahead; the ego slows to its speed.
    world, car = _world("cut_in", "straight", 2, speed, seed)
    v = _speeds(world, t)
    y_e = _ego_pose(world, 0.0)[0][1]
    assert abs(abs(car.trajectory.pose(0.0)[0][1] - y_e) - 3.5) < 0.1
    assert abs(car.trajectory.pose(t[-1])[0][1] - y_e) < 0.1
    assert car.trajectory.pose(t[-1])[0][0] > _ego_pose(world, t[-1])[0][0]
    assert 0.3 * speed <= v[-1] <= 0.65 * speed and v[-1] == pytest.approx(
        car.trajectory.speed(t[-1]), abs=0.2
    )
    # ped_crossing: the ego stands >= 1 s while the pedestrian crosses its lane ahead, then goes.
    world, ped = _world("ped_crossing", "straight", 2, speed, seed)
    v = _speeds(world, t)
    assert _standing(v, t) >= 1.0 and v[-1] > 3.0
    py = ped.trajectory.pose(t)[0][:, 1]
    cross = int(np.argmin(np.abs(py - _ego_pose(world, 0.0)[0][1])))
    assert ped.trajectory.pose(t[cross])[0][0] > _ego_pose(world, t[cross])[0][0] + 3.0
    # turn_oncoming: the ego waits inside the junction, yawed, while the car passes; then turns.
    world, car = _world("turn_oncoming", "intersection", 2, speed, seed)
    v = _speeds(world, t)
    standing = v < 0.2
    assert _standing(v, t) >= 0.5
    xy, yaw = _ego_pose(world, t)
    assert np.degrees(yaw[standing]).min() > 3.0 and np.degrees(yaw[standing]).max() < 60.0
    cx = car.trajectory.pose(t)[0][:, 0]
    passes = standing & (cx < xy[:, 0])
    assert passes.any() and (cx[standing] > xy[standing, 0]).any()
    assert np.degrees(_ego_pose(world, world.duration + 4.0)[1]) > 60.0
    # overtake_parked: the ego slows and is >= 2.5 m left of its lane beside the parked car.
    world, car = _world("overtake_parked", "straight", 2, speed, seed)
    v = _speeds(world, t)
    xy, _ = _ego_pose(world, t)
    y_e = xy[0, 1]
    assert not car.moving and v.min() < 0.9 * speed
    beside = np.argmin(np.abs(xy[:, 0] - car.trajectory.xy[0, 0]))
    assert xy[beside, 1] - y_e >= 2.5
    # ... and holds its slow speed while alongside (rear axle from the car's rear to its front).
    x_car, half = car.trajectory.xy[0, 0], car.size[1] / 2
    alongside = (xy[:, 0] >= x_car - half) & (xy[:, 0] <= x_car + half)
    assert alongside.any() and np.ptp(v[alongside]) < 0.05 and v[alongside].max() < 0.9 * speed
    assert abs(_ego_pose(world, world.duration + 4.0)[0][1] - y_e) < 0.3


def test_scripted_scene_is_deterministic():
    a, _ = _world("turn_oncoming", "intersection", 2, 9.0, 5)
    b, _ = _world("turn_oncoming", "intersection", 2, 9.0, 5)
    c, _ = _world("turn_oncoming", "intersection", 2, 9.0, 6)
    assert np.array_equal(a.ego.trajectory.xy, b.ego.trajectory.xy)
    assert np.array_equal(a.ego.scripted[0].trajectory.xy, b.ego.scripted[0].trajectory.xy)
    assert not np.array_equal(a.ego.trajectory.xy, c.ego.trajectory.xy)


@pytest.mark.parametrize(
    "scene, match",
    [
        (dict(kind="curve", behaviour="lead_brake"), r"s\[0\].kind: expected one of \('straig"),
        (dict(kind="straight", behaviour="turn_oncoming"), r"kind: .*for turn_oncoming"),
        (dict(kind="t_junction", behaviour="ped_crossing"), r"kind: .*for ped_crossing"),
        (dict(behaviour="cut_in", lanes=1), r"scenes\[0\].lanes: expected 2 for cut_in"),
        (dict(behaviour="overtake_parked", speed=3.0), r"speed: expected a speed in \[5, 15\]"),
        (dict(behaviour="lead_brake", route=[[0, 0], [50, 0]]), r"route: expected no explicit"),
        (dict(behaviour="ped_crossing", effects={"agent_motion": False}), r"effects: expected"),
    ],
)
def test_interaction_validation_names_the_field(scene, match):
    with pytest.raises(ValueError, match=match):
        SimConfig.from_dict({"keyframes": K, "scenes": [scene]})


def test_interaction_needs_keyframes():
    with pytest.raises(ValueError, match=r"keyframes: expected >= 16 for scenes\[0\].behaviour"):
        SimConfig.from_dict({"keyframes": 12, "scenes": [{"behaviour": "lead_brake"}]})
    with pytest.raises(ValueError, match=r"keyframes: expected >= 16 for behaviour 'cut_in'"):
        build_world("s", SceneSpec(behaviour="cut_in"), 12, 0, 0)


def test_presets_load_validate_and_split(tmp_path):
    lib, held = config_from_preset("scenarios"), config_from_preset("interactions")
    assert lib.seed != held.seed and lib.version != held.version
    assert 60 <= len(lib.scenes) <= 120 and 12 <= len(held.scenes) <= 20
    assert min(lib.keyframes, held.keyframes) >= 20
    seen = Counter(s.behaviour for s in lib.scenes)
    for b in (*INTERACTIONS, "turn_left", "turn_right", "cruise", "lane_change_left"):
        assert seen[b] >= 4, b
    assert len({s.speed for s in lib.scenes}) > 20
    assert {s.behaviour for s in held.scenes} == set(INTERACTIONS)
    assert set(n for n, _ in lib.named_scenes).isdisjoint(n for n, _ in held.named_scenes)
    for cfg, split in ((lib, "train"), (held, "val")):
        names = [n for n, _ in cfg.named_scenes]
        assert cfg.split_lists() == {split: names}
        # What the infos builder reads from <version>/splits.json.
        vdir = tmp_path / cfg.version
        vdir.mkdir()
        (vdir / "splits.json").write_bytes(cfg.splits_json())
        assert set(assign_splits(names, vdir, strict=True).values()) == {split}
        assert json.loads(cfg.splits_json()) == {split: names}
    # A num_scenes override keeps the split rule; the first scenes of each build.
    few = config_from_preset("scenarios", num_scenes=3)
    assert few.split_lists() == {"train": ["scene-5000", "scene-5001", "scene-5002"]}
    more = config_from_preset("interactions", num_scenes=20)
    assert more.split_lists()["val"][-1] == "scene-9019"
    assert len(build_worlds(config_from_preset("interactions", num_scenes=2))) == 2


def test_splits_must_cover_each_scene_once():
    names = ["scene-5000", "scene-6000"]
    scenes = [{}, {}]
    with pytest.raises(ValueError, match=r"splits: expected exactly one split matching scene "):
        SimConfig.from_dict({"scenes": scenes, "scene_names": names, "splits": {"t": ["*-5*"]}})
    with pytest.raises(ValueError, match=r"splits: expected exactly one split matching"):
        SimConfig.from_dict(
            {"scenes": scenes, "scene_names": names, "splits": {"a": ["*"], "b": ["scene-6*"]}}
        )
    with pytest.raises(ValueError, match=r"splits: expected \{split: \[scene-name patterns\]\}"):
        SimConfig.from_dict({"scenes": scenes, "scene_names": names, "splits": {"a": "scene-*"}})
    cfg = SimConfig.from_dict(
        {"scenes": scenes, "scene_names": names, "splits": {"train": ["scene-5*"], "val": ["*-6*"]}}
    )
    assert cfg.split_lists() == {"train": ["scene-5000"], "val": ["scene-6000"]}


def test_written_dataset_ships_its_split(tmp_path):
    """The held-out preset, simulated (occupancy only), is all val for the infos builder."""
    from renderworld.sim import simulate

    cfg = config_from_preset("interactions", num_scenes=1, mode="occupancy")
    simulate(cfg, tmp_path / "data", progress=False)
    vdir = tmp_path / "data" / cfg.version
    assert json.loads((vdir / "splits.json").read_text()) == {"val": ["scene-6000"]}
    assert assign_splits(["scene-6000"], vdir, strict=True) == {"scene-6000": "val"}
    scene = json.loads((vdir / "scene.json").read_text())[0]
    assert scene["nbr_samples"] == cfg.keyframes and "lead brake" in scene["description"]


def test_speed_targets_see_the_distance_from_the_position_at_t0():
    from renderworld.sim.layout import motion_times
    from renderworld.sim.scenarios import integrate_speed

    seen = []

    def target(t, s):
        seen.append((t, s))
        return (10.0, 1.0, 1.0) if s < 20.0 else (5.0, 1.0, 1.0)  # slow down from 20 m on

    times = motion_times(10.0)
    s, v = integrate_speed(times, 10.0, target)
    at = {round(t, 3): x for t, x in seen}
    assert at[0.0] == pytest.approx(0.0, abs=1e-9)
    assert abs(s[np.argmin(np.abs(times))]) < 1e-9
    assert at[1.0] == pytest.approx(10.0, abs=1e-6)  # 1 s at 10 m/s: 10 m past the t = 0 spot
    first_slow = times[np.argmax(v < 10.0 - 1e-9)]
    assert 2.0 <= first_slow <= 2.0 + 3 * (times[1] - times[0])  # 20 m at 10 m/s
