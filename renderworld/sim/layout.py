"""Procedural scene layout: roads, the ego route and static objects from a :class:`SceneSpec`.

Everything is in the scene's local frame (metres; x east, y north, z up; flat ground z = 0).
The ego starts at the origin heading +x in a right-hand lane. Randomness comes only from the
generator passed in, so a seed fixes the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from renderworld.constants import EGO_CENTRE_OFFSET, EGO_LENGTH, EGO_WIDTH, KEYFRAME_DT
from renderworld.sim.agents import DT_MOTION, Path, Trajectory, arc_path, rects_overlap
from renderworld.sim.objects import SimObject, make_object
from renderworld.sim.roads import ROAD, TERRAIN, GroundRaster, Junction, Road, RoadNetwork
from renderworld.sim.scene import SceneSpec

__all__ = [
    "World",
    "EgoPlan",
    "build_roads",
    "plan_ego",
    "place_static",
    "ego_trajectory",
    "ego_box_at",
    "EGO_CENTRE_OFFSET",
    "TURN_TRANSITION_M",
    "CURVE_TRANSITION_M",
]

# Clothoid lengths into and out of every arc (the curvature ramps, as steering and road design do):
TURN_TRANSITION_M = 6.0  # junction turns: about 1 s of steering at the 5.5 m/s turning speed
CURVE_TRANSITION_M = 20.0  # road curves (radius 45-70 m), driven at cruising speed


def ego_box_at(xy, yaw) -> tuple[np.ndarray, np.ndarray]:
    """Ego box centre [..., 2] and yaw [...] of rear-axle poses ``xy`` [..., 2], ``yaw`` [...]."""
    xy, yaw = np.asarray(xy, dtype=np.float64), np.asarray(yaw, dtype=np.float64)
    return xy + EGO_CENTRE_OFFSET * np.stack([np.cos(yaw), np.sin(yaw)], -1), yaw


@dataclass
class EgoPlan:
    """The ego route: its path, trajectory (rear-axle pose) and behaviour landmarks."""

    path: Path
    trajectory: Trajectory
    junction_x: float = 0.0  # x of the junction or curve start, metres
    lane_offset: float = 0.0  # metres right of the road centreline
    turn_window: tuple[float, float] | None = None  # arc lengths driven at turning speed
    v_turn: float = 0.0
    stop_s: float | None = None  # arc length where a stop-and-go ego stands
    stop_window: tuple[float, float] | None = None  # seconds
    scripted: list = field(default_factory=list)  # agents of an interaction scenario


@dataclass
class World:
    """A generated scene: roads, ground raster, ego, objects and lighting."""

    name: str
    spec: SceneSpec
    network: RoadNetwork
    raster: GroundRaster
    ego: EgoPlan
    objects: list[SimObject] = field(default_factory=list)
    duration: float = 0.0
    sun: np.ndarray = field(default_factory=lambda: np.array([0.3, 0.4, 0.87]))
    lamps: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def ego_box(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Ego box centre [..., 2] and yaw [...] at time(s) ``t``."""
        return ego_box_at(*self.ego.trajectory.pose(t))


def build_roads(spec: SceneSpec, junction_x: float, rng: np.random.Generator) -> RoadNetwork:
    """Road network of ``spec.kind``; junctions/curves start ``junction_x`` metres ahead."""
    mk = dict(lanes=spec.lanes, lane_width=3.5, parking=2.5, sidewalk=3.0)
    far = 400.0
    if spec.kind == "straight":
        return RoadNetwork([Road(np.array([[-far, 0.0], [far, 0.0]]), **mk)])
    if spec.kind == "curve":
        angle = np.deg2rad(rng.uniform(60, 90)) * rng.choice([-1.0, 1.0])
        radius = rng.uniform(45, 70)
        pieces = [("line", far + junction_x, 0), ("arc", radius, angle), ("line", far, 0)]
        pts = arc_path((-far, 0.0), 0.0, pieces, transition=CURVE_TRANSITION_M)
        return RoadNetwork([Road(pts, **mk)])
    hw = Road(np.zeros((2, 2)), **mk).half_width
    a_end = far if spec.kind == "intersection" else junction_x
    road_a = Road(np.array([[-far, 0.0], [a_end, 0.0]]), **mk)
    road_b = Road(np.array([[junction_x, -far], [junction_x, far]]), **mk)
    arms = ("+x", "-x", "+y", "-y") if spec.kind == "intersection" else ("-x", "+y", "-y")
    return RoadNetwork([road_a, road_b], [Junction((junction_x, 0.0), arms, hw, hw)])


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


def plan_ego(spec: SceneSpec, duration: float, rng: np.random.Generator) -> EgoPlan:
    """The ego path (rear-axle positions) and where its turn, curve or junction lies.

    The junction (or curve start) is placed so that the ego reaches it 25-40 % into the scene.
    """
    v = float(spec.speed)
    road = Road(np.zeros((2, 2)), lanes=spec.lanes)
    hw = road.half_width
    left = spec.behaviour in ("turn_left", "turn_oncoming")
    lanes = {"turn_left": 0, "turn_oncoming": 0, "turn_right": spec.lanes - 1,
             "lane_change_left": 0, "overtake_parked": spec.lanes - 1}  # fmt: skip
    lane = lanes.get(spec.behaviour, 1 if spec.behaviour == "lane_change_right" else None)
    if lane is None:
        lane = int(rng.integers(spec.lanes))
    lane = min(lane, spec.lanes - 1)
    o = -road.lane_offset(lane)  # metres right of the centreline
    approach = v * duration * rng.uniform(0.25, 0.4)
    tail = v * (duration + 4.0) + 60.0
    r_turn = hw + o if left else 9.0
    junction_x = approach + (hw if left else o + r_turn)
    if spec.kind == "curve":
        junction_x = approach
    turn_window = None
    if left or spec.behaviour == "turn_right":
        sign = 1.0 if left else -1.0
        pieces = [("line", approach, 0), ("arc", r_turn, sign * np.pi / 2), ("line", tail, 0)]
        path = Path(arc_path((0.0, -o), 0.0, pieces, transition=TURN_TRANSITION_M))
        turn_window = (approach - 15.0, approach + r_turn * np.pi / 2 + 10.0)
    else:
        path = Path(np.array([[0.0, -o], [tail, -o]]))
        if spec.behaviour.startswith("lane_change"):
            d = road.lane_width if spec.behaviour == "lane_change_left" else -road.lane_width
            s0 = v * duration * rng.uniform(0.2, 0.35)
            path = path.offset(lambda s: d * _smoothstep((s - s0) / (2.8 * v)))
    plan = EgoPlan(path=path, trajectory=None)  # type: ignore[arg-type]
    plan.junction_x = junction_x
    plan.lane_offset = o
    plan.turn_window = turn_window
    plan.v_turn = min(v, 5.5) if turn_window else v
    return plan


def time_ego(plan: EgoPlan, spec: SceneSpec, times: np.ndarray, rng) -> None:
    """Integrate the ego speed profile along its path; fills ``plan.trajectory``."""
    v = float(spec.speed)
    if not spec.effects.ego_motion or spec.behaviour == "parked":
        xy, h = plan.path.at(np.zeros(1))
        plan.trajectory = Trajectory.fixed(times, xy[0, 0], xy[0, 1], float(h[0]))
        return
    s = np.zeros_like(times)
    stop = None
    if spec.behaviour == "stop_and_go":
        t_brake = times[-1] * rng.uniform(0.15, 0.3)
        t_go = t_brake + v / 2.5 + rng.uniform(2.0, 3.0)
        stop = (t_brake, t_brake + v / 2.5, t_go)
    i0 = int(np.searchsorted(times, 0.0))
    sp = v
    for i in range(i0 + 1, len(times)):
        t, dt = times[i - 1], times[i] - times[i - 1]
        target = v
        if plan.turn_window is not None and plan.turn_window[0] <= s[i - 1] <= plan.turn_window[1]:
            target = plan.v_turn
        if stop is not None and stop[0] <= t < stop[2]:
            target = 0.0
        # Comfortable longitudinal dynamics: brake <= 2.5 m/s^2, accelerate <= 1.5 m/s^2.
        sp = float(np.clip(target, sp - 2.5 * dt, sp + 1.5 * dt))
        s[i] = s[i - 1] + sp * dt
    s[:i0] = v * times[:i0] if stop is None else 0.0
    plan.trajectory = ego_trajectory(plan.path, s, times)
    if stop is not None:
        plan.stop_s = float(s[np.searchsorted(times, stop[1])])
        plan.stop_window = (float(stop[1]), float(stop[2]))


def ego_trajectory(path: Path, s: np.ndarray, times: np.ndarray) -> Trajectory:
    """Rear-axle trajectory along ``path`` at arc lengths ``s`` [T] (metres; < 0 before its start).

    The path is extended 20 m straight backwards so that poses before t = 0 exist.
    """
    (p0,), (h0,) = path.at(np.zeros(1))
    back = p0 - 20.0 * np.array([np.cos(h0), np.sin(h0)])
    ext = Path(np.concatenate([back[None], path.xy]))
    return Trajectory.along(ext, np.asarray(s) + 20.0, times)


def _free(world: World, key, centre, yaw, half, margin=0.3) -> bool:
    """Whether a static footprint misses every object placed so far and the ego route."""
    for obj in world.objects:
        if obj.moving:  # a scripted agent: its whole path, 0.1 s steps
            c, y = obj.trajectory.xy[::5], obj.trajectory.yaw[::5]
            if rects_overlap(c, y, obj.footprint_half() + margin, centre, yaw, half).any():
                return False
            continue
        c, y = obj.trajectory.xy[0], obj.trajectory.yaw[0]
        if np.hypot(*(c - centre)) > np.hypot(*half) + np.hypot(*obj.footprint_half()) + margin:
            continue
        if rects_overlap(c, y, obj.footprint_half() + margin, centre, yaw, half):
            return False
    t = np.linspace(0, world.duration + 3.0, 80)
    ec, ey = world.ego_box(t)
    ego_half = np.array([EGO_LENGTH / 2 + 1.0, EGO_WIDTH / 2 + 0.5])
    return not rects_overlap(ec, ey, ego_half, centre, yaw, half).any()


def _on(world: World, centre, yaw, half, classes) -> bool:
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-np.sin(yaw), np.cos(yaw)])
    g = np.linspace(-1, 1, 5)
    pts = centre + g[:, None, None] * half[0] * u + g[None, :, None] * half[1] * v
    return bool(np.isin(world.raster.classify(pts.reshape(-1, 2)), classes).all())


def _try_add(world, rng, key, cat, size, centre, yaw, classes, variant=""):
    half = np.array([size[1] / 2, size[0] / 2])
    if variant == "tree":
        half = np.array([0.3, 0.3])
    if not _on(world, centre, yaw, half, classes) or not _free(world, key, centre, yaw, half):
        return False
    traj = Trajectory.fixed(np.array([-1.0, world.duration + 5.0]), centre[0], centre[1], yaw)
    world.objects.append(make_object(key, cat, size, traj, rng, variant=variant))
    return True


def place_static(world: World, rng: np.random.Generator) -> None:
    """Buildings, trees, hedges, poles, props and parked vehicles along every road."""
    spec = world.spec
    x0, y0 = world.raster.x0, world.raster.y0
    x1 = x0 + world.raster.shape[0] * world.raster.cell
    y1 = y0 + world.raster.shape[1] * world.raster.cell
    n = 0
    for _r, road in enumerate(world.network.roads):
        path = Path(road.points)
        inside = (
            (path.xy[:, 0] > x0)
            & (path.xy[:, 0] < x1)
            & (path.xy[:, 1] > y0)
            & (path.xy[:, 1] < y1)
        )
        if not inside.any():
            continue
        s_lo, s_hi = path.s[inside].min(), path.s[inside].max()
        for side in (-1.0, 1.0):
            kerb = road.half_width + road.sidewalk
            # Buildings (density: num_buildings per 100 m of road side).
            s = s_lo + rng.uniform(0, 10)
            while s < s_hi and spec.num_buildings > 0:
                width = rng.uniform(8, 20)
                depth, height = rng.uniform(8, 16), rng.uniform(6, 24)
                setback = rng.uniform(3, 8)
                (p,), (h,) = path.at([s + width / 2])
                nrm = side * np.array([-np.sin(h), np.cos(h)])
                c = p + nrm * (kerb + setback + depth / 2)
                if rng.random() < min(spec.num_buildings / 8.0, 1.0):
                    _try_add(
                        world,
                        rng,
                        f"bld{n}",
                        "static.manmade",
                        (depth, width, height),
                        c,
                        h,
                        [TERRAIN],
                    )
                n += 1
                s += width + rng.uniform(2, 8) * 8.0 / max(spec.num_buildings, 1)
            # Trees, hedges and lamp poles on the verge.
            s = s_lo + rng.uniform(0, 8)
            step = 100.0 / max(spec.num_trees, 1)
            while s < s_hi and spec.num_trees > 0:
                (p,), (h,) = path.at([s])
                nrm = side * np.array([-np.sin(h), np.cos(h)])
                if rng.random() < 0.75:
                    r_c = rng.uniform(1.2, 2.2)
                    c = p + nrm * (kerb + rng.uniform(1.0, 2.5))
                    size = (2 * r_c, 2 * r_c, rng.uniform(5, 9))
                    _try_add(
                        world, rng, f"veg{n}", "static.vegetation", size, c, h, [TERRAIN], "tree"
                    )
                else:
                    size = (rng.uniform(0.8, 1.2), rng.uniform(3, 9), rng.uniform(1.0, 1.8))
                    c = p + nrm * (kerb + 1.2)
                    _try_add(
                        world, rng, f"veg{n}", "static.vegetation", size, c, h, [TERRAIN], "hedge"
                    )
                n += 1
                s += step * rng.uniform(0.6, 1.4)
            for s in np.arange(s_lo + rng.uniform(0, 25), s_hi, 28.0):
                (p,), (h,) = path.at([s])
                c = p + side * np.array([-np.sin(h), np.cos(h)]) * (road.half_width + 0.5)
                _try_add(world, rng, f"pole{n}", "static.manmade", (0.25, 0.25, 7.0), c, h,
                         [26], "pole")  # fmt: skip
                n += 1
    _place_parked_and_props(world, rng)


def _place_parked_and_props(world: World, rng: np.random.Generator) -> None:
    spec = world.spec
    road = world.network.roads[0]
    path = Path(road.points)
    s_ego, _ = path.project(world.ego.trajectory.xy[:1])
    s_lo, s_hi = s_ego[0] - 30.0, s_ego[0] + spec.speed * world.duration + 50.0
    junctions = [np.asarray(j.centre) for j in world.network.junctions]
    cats = ["vehicle.car"] * 6 + ["vehicle.truck", "vehicle.trailer", "vehicle.bicycle",
                                  "vehicle.motorcycle", "vehicle.construction"]  # fmt: skip
    from renderworld.sim.scene import OBJECT_CATEGORIES

    placed, tries = 0, 0
    while placed < spec.num_parked and tries < 20 * spec.num_parked + 20:
        tries += 1
        side = rng.choice([-1.0, 1.0])
        s = rng.uniform(s_lo, s_hi)
        (p,), (h,) = path.at([s])
        if any(np.hypot(*(p - j)) < road.half_width * 2 + 12 for j in junctions):
            continue
        cat = cats[int(rng.integers(len(cats)))]
        w, ln, hh = OBJECT_CATEGORIES[cat]
        size = (min(w, 2.3), ln * rng.uniform(0.9, 1.1), hh * rng.uniform(0.92, 1.08))
        c = p + side * np.array([-np.sin(h), np.cos(h)]) * road.parking_offset(1.0)
        yaw = h if side < 0 else h + np.pi
        placed += _try_add(world, rng, f"park{tries}", cat, size, c, yaw, [ROAD])
    # A small work zone: a line of cones and barriers in a parking strip.
    for k in range(spec.num_props):
        side = -1.0 if k % 2 == 0 else 1.0
        s = s_lo + 40 + (k // 2) * 4.0 + rng.uniform(0, 1)
        (p,), (h,) = path.at([s])
        c = p + side * np.array([-np.sin(h), np.cos(h)]) * road.parking_offset(1.0)
        cat = "movable_object.trafficcone" if k % 3 else "movable_object.barrier"
        _try_add(world, rng, f"prop{k}", cat, OBJECT_CATEGORIES[cat], c, h, [ROAD])


def keyframe_times(keyframes: int) -> np.ndarray:
    """Keyframe times [K] seconds from the scene start (2 Hz)."""
    return np.arange(keyframes) * KEYFRAME_DT


def motion_times(duration: float) -> np.ndarray:
    """Dense trajectory sample times covering [-1 s, duration + 4 s]."""
    return np.arange(-1.0, duration + 4.0 + DT_MOTION / 2, DT_MOTION)
