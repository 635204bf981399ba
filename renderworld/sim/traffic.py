"""Traffic and the assembled world: moving vehicles, pedestrians, explicit objects, validation.

Vehicles follow lanes at a per-lane speed (so followers keep their gap); cross traffic at a
junction queues at the stop line; pedestrians walk along sidewalks or cross the road. Every
candidate agent is checked against the ego, static objects and accepted agents over the whole
scene (oriented boxes, 0.1 s steps) and dropped if it would ever overlap one.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import EGO_LENGTH, EGO_WIDTH
from renderworld.sim.agents import Path, Trajectory, rects_overlap
from renderworld.sim.layout import (
    World,
    build_roads,
    keyframe_times,
    motion_times,
    place_static,
    plan_ego,
    time_ego,
)
from renderworld.sim.objects import make_object
from renderworld.sim.roads import ROAD, GroundRaster
from renderworld.sim.scenarios import INTERACTIONS, plan_interaction
from renderworld.sim.scene import MIN_INTERACTION_KEYFRAMES, OBJECT_CATEGORIES, SceneSpec

__all__ = ["build_world", "ego_route"]

_MOVING = ["vehicle.car"] * 7 + ["vehicle.truck", "vehicle.bus.rigid", "vehicle.motorcycle",
                                 "vehicle.bicycle", "vehicle.car"]  # fmt: skip


def build_world(name: str, spec: SceneSpec, keyframes: int, seed: int, index: int) -> World:
    """Generate (and validate) one scene.

    Args:
        name: scene name.
        spec: the scene description (validated here).
        keyframes: number of 2 Hz keyframes.
        seed: master seed.
        index: scene index (mixed into the seed).

    Raises:
        ValueError: on an invalid description, an explicit route leaving the road or
            overlapping explicit static objects.
    """
    plan, network, rng, times = ego_route(spec, keyframes, seed, index)
    duration = float(keyframe_times(keyframes)[-1])
    visible = plan.trajectory.pose(np.linspace(0, duration, 50))[0]
    lo, hi = visible.min(0) - 80.0, visible.max(0) + 80.0
    raster = GroundRaster(network, (lo[0], lo[1], hi[0], hi[1]))
    world = World(name=name, spec=spec, network=network, raster=raster, ego=plan, duration=duration)
    _check_route(world)
    _add_explicit(world, rng)
    _add_scripted(world)
    place_static(world, rng)
    if spec.num_moving:
        _add_vehicles(world, rng, times)
    if spec.num_pedestrians:
        _add_pedestrians(world, rng, times)
    if not spec.effects.agent_motion:
        for obj in world.objects:  # freeze every agent at its start pose
            if obj.moving:
                (xy, yaw) = obj.trajectory.pose(0.0)
                obj.trajectory = Trajectory.fixed(times, xy[0], xy[1], float(yaw))
                obj.moving = False
    az, el = rng.uniform(0, 2 * np.pi), rng.uniform(np.deg2rad(30), np.deg2rad(65))
    world.sun = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    world.lamps = np.array(
        [[*o.trajectory.xy[0], 6.8] for o in world.objects if o.key.startswith("pole")]
    ).reshape(-1, 3)
    return world


def ego_route(spec: SceneSpec, keyframes: int, seed: int, index: int):
    """The ego's route and road network of a scene, without objects or sensors (cheap).

    :func:`build_world` starts with exactly this, so the trajectories agree.

    Returns:
        ``(plan: EgoPlan, network: RoadNetwork, rng, times [T] s)``; ``plan.trajectory`` holds
        the rear-axle pose over time (scene frame).
    """
    spec.validate("scene")
    if isinstance(keyframes, bool) or not isinstance(keyframes, int) or keyframes < 1:
        raise ValueError(f"keyframes: expected an integer >= 1, got {keyframes}")
    rng = np.random.default_rng([seed, index, 7])
    duration = float(keyframe_times(keyframes)[-1])
    times = motion_times(duration)
    plan = plan_ego(spec, duration, rng)
    network = build_roads(spec, plan.junction_x, rng)
    if spec.kind == "curve" and spec.route is None:
        full = Path(network.roads[0].points).offset(-plan.lane_offset)
        s0, _ = full.project(np.array([[0.0, -plan.lane_offset]]))
        plan.path = Path(full.xy[full.s >= s0[0]])
    if spec.route is not None:
        plan.path = Path(np.asarray(spec.route, dtype=np.float64))
    if spec.behaviour in INTERACTIONS:
        if keyframes < MIN_INTERACTION_KEYFRAMES:
            raise ValueError(
                f"keyframes: expected >= {MIN_INTERACTION_KEYFRAMES} for behaviour "
                f"{spec.behaviour!r}, got {keyframes}"
            )
        plan_interaction(plan, spec, network.roads[0], times, keyframes, rng)
    else:
        time_ego(plan, spec, times, rng)
    return plan, network, rng, times


def _check_route(world: World) -> None:
    """Every point the ego drives (and every sample of an explicit route) must be road."""
    t = np.linspace(0.0, world.duration, max(int(world.duration * 10), 2))
    xy, _ = world.ego.trajectory.pose(t)
    if world.spec.route is not None:
        xy = np.concatenate([world.ego.path.xy, xy])
    bad = np.nonzero(world.raster.classify(xy) != ROAD)[0]
    if len(bad):
        p = xy[bad[0]]
        raise ValueError(
            f"route: the ego route leaves the driveable surface at ({p[0]:.1f}, {p[1]:.1f}) m; "
            "expected every route point on the road"
        )


def _add_explicit(world: World, rng) -> None:
    objs = world.spec.objects
    for i, o in enumerate(objs):
        w, ln, _ = o.dims
        half_i = np.array([ln / 2, w / 2])
        for j in range(i):
            q = objs[j]
            half_j = np.array([q.dims[1] / 2, q.dims[0] / 2])
            if rects_overlap([o.x, o.y], o.yaw, half_i, [q.x, q.y], q.yaw, half_j):
                raise ValueError(
                    f"scene.objects[{i}]: overlaps static object scene.objects[{j}] "
                    f"({o.category} at ({o.x}, {o.y}) vs {q.category} at ({q.x}, {q.y})); "
                    "expected non-overlapping static objects"
                )
        t = np.linspace(0, world.duration, 60)
        ec, ey = world.ego_box(t)
        if rects_overlap(ec, ey, [EGO_LENGTH / 2, EGO_WIDTH / 2], [o.x, o.y], o.yaw, half_i).any():
            raise ValueError(
                f"scene.objects[{i}]: {o.category} at ({o.x}, {o.y}) blocks the ego route; "
                "expected static objects off the ego's path"
            )
        traj = Trajectory.fixed(np.array([-1.0, world.duration + 5.0]), o.x, o.y, o.yaw)
        variant = "tree" if o.category == "static.vegetation" else ""
        world.objects.append(make_object(f"obj{i}", o.category, o.dims, traj, rng, variant=variant))


def _add_scripted(world: World) -> None:
    """The interaction agent (already clear of the ego route) must miss the explicit objects."""
    check = np.arange(-0.5, world.duration + 3.5, 0.1)
    for obj in world.ego.scripted:
        hit = [o.key for o in world.objects if _overlaps(obj, o, check, 0.0)]
        if hit:
            raise ValueError(
                f"scene.objects: explicit object {hit[0]} overlaps the {world.spec.behaviour} "
                f"agent {obj.key}; expected explicit objects off the scripted agent's path"
            )
        world.objects.append(obj)


def _overlaps(obj, other, times_check: np.ndarray, margin: float) -> bool:
    c, y = obj.trajectory.pose(times_check)
    half = obj.footprint_half() + margin
    oc, oy = other.trajectory.pose(times_check)
    reach = np.hypot(*half) + np.hypot(*other.footprint_half()) + 0.1
    near = np.hypot(*(oc - c).T) < reach
    return bool(
        near.any()
        and rects_overlap(c[near], y[near], half, oc[near], oy[near], other.footprint_half()).any()
    )


def _accept(world: World, obj, times_check: np.ndarray, margin: float = 0.25) -> bool:
    """Whether a moving candidate never overlaps the ego or any object already in the world."""
    c, y = obj.trajectory.pose(times_check)
    half = obj.footprint_half() + margin
    ec, ey = world.ego_box(times_check)
    if rects_overlap(c, y, half, ec, ey, [EGO_LENGTH / 2 + 0.5, EGO_WIDTH / 2 + 0.3]).any():
        return False
    return not any(_overlaps(obj, other, times_check, margin) for other in world.objects)


def _lane_path(road, lane: int, forward: bool) -> Path:
    pts = road.points if forward else road.points[::-1]
    return Path(pts).offset(road.lane_offset(lane))


def _add_vehicles(world: World, rng, times: np.ndarray) -> None:
    spec = world.spec
    check = np.arange(-0.5, world.duration + 3.5, 0.1)
    lanes = []  # (road index, lane, forward, stops_at_junction)
    for r, road in enumerate(world.network.roads):
        for lane in range(road.lanes):
            for fwd in (True, False):
                cross = r > 0 and bool(world.network.junctions)
                lanes.append((r, lane, fwd, cross))
    speeds = {k: rng.uniform(6.0, 11.0) for k in range(len(lanes))}
    placed, tries = 0, 0
    ego_xy = world.ego.trajectory.pose(np.linspace(0, world.duration, 20))[0]
    while placed < spec.num_moving and tries < 12 * spec.num_moving:
        tries += 1
        k = int(rng.integers(len(lanes)))
        r, lane, fwd, cross = lanes[k]
        road = world.network.roads[r]
        path = _lane_path(road, lane, fwd)
        s_near, _ = path.project(ego_xy)
        cat = _MOVING[int(rng.integers(len(_MOVING)))]
        w, ln, h = OBJECT_CATEGORIES[cat]
        size = (w, ln * rng.uniform(0.92, 1.08), h * rng.uniform(0.95, 1.05))
        v = speeds[k] * (0.6 if cat == "vehicle.bicycle" else 1.0)
        if cross:
            j = world.network.junctions[0]
            s_j, _ = path.project(np.asarray(j.centre)[None])
            s_stop = s_j[0] - j.half_width_x - 3.0 - ln / 2 - rng.uniform(0, 25)
            dist = rng.uniform(8, 50)
            s_t = s_stop - dist * np.exp(-v * np.maximum(times, 0) / dist)
        else:
            s0 = rng.uniform(s_near.min() - 30, s_near.max() + 40)
            s0 = s0 - (v * world.duration if not fwd else 0.0) * rng.uniform(0, 0.6)
            s_t = s0 + v * times
        traj = Trajectory.along(path, s_t, times)
        obj = make_object(f"veh{tries}", cat, size, traj, rng, moving=True)
        if _accept(world, obj, check):
            world.objects.append(obj)
            placed += 1


def _add_pedestrians(world: World, rng, times: np.ndarray) -> None:
    spec = world.spec
    check = np.arange(-0.5, world.duration + 3.5, 0.1)
    road = world.network.roads[0]
    centre = Path(road.points)
    ego_xy = world.ego.trajectory.pose(np.linspace(0, world.duration, 20))[0]
    s_ego, _ = centre.project(ego_xy)
    placed, tries = 0, 0
    size = OBJECT_CATEGORIES["human.pedestrian.adult"]
    while placed < spec.num_pedestrians and tries < 12 * spec.num_pedestrians:
        tries += 1
        h = rng.uniform(1.55, 1.9)
        v = rng.uniform(0.9, 1.6) if rng.random() < 0.8 else 0.0
        crossing = rng.random() < 0.3 or (world.ego.stop_window is not None and placed < 2)
        if crossing:
            # Cross the road on a line ahead of the ego (in front of a stopped ego if any).
            if world.ego.stop_s is not None and placed < 2:
                s_line = s_ego.min() + world.ego.stop_s + 7.0 + rng.uniform(0, 1.5)
                t_start = world.ego.stop_window[0] - rng.uniform(1.0, 3.0)
            else:
                s_line = rng.uniform(s_ego.min() + 10, s_ego.max() + 30)
                t_start = rng.uniform(-5.0, world.duration)
            (p,), (hd,) = centre.at([s_line])
            nrm = np.array([-np.sin(hd), np.cos(hd)]) * rng.choice([-1.0, 1.0])
            reach = road.half_width + road.sidewalk * 0.5
            line = Path(np.stack([p - nrm * reach, p + nrm * reach]))
            s_t = np.clip((times - t_start) * max(v, 1.1), 0.0, line.length)
            traj = Trajectory.along(line, s_t, times)
        else:
            side = rng.choice([-1.0, 1.0])
            off = side * (road.half_width + road.sidewalk * rng.uniform(0.3, 0.7))
            fwd = rng.random() < 0.5
            walk = Path(road.points if fwd else road.points[::-1]).offset(off if fwd else -off)
            s_w, _ = walk.project(ego_xy)
            s0 = rng.uniform(s_w.min() - 20, s_w.max() + 30)
            traj = Trajectory.along(walk, s0 + v * times, times)
        obj = make_object(
            f"ped{tries}", "human.pedestrian.adult", (size[0], size[1], h), traj, rng, moving=True
        )
        if _accept(world, obj, check, margin=0.1):
            world.objects.append(obj)
            placed += 1
