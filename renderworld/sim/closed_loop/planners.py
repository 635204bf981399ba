"""Planners that drive in closed loop: reference planners and any planner bundle.

Every planner answers :meth:`plan` with the planner API's trajectory convention
(:class:`renderworld.planning.PlanResult`): [6, 2] metres, positions at +0.5 ... +3.0 s in the
**current** ego frame (x forward, y left, rear axle).

* ``log_replay``: the logged ego's future positions (reads the log: the runner's self-check).
* ``cv``: constant velocity, the last history displacement repeated
  (:func:`renderworld.world.baselines.constant_velocity_trajectory`).
* ``ctr``: constant turn rate, the last displacement and heading change repeated
  (:func:`renderworld.world.baselines.constant_turn_rate_trajectory`).
* ``rule_based``: **privileged reference** (:class:`RuleBased`): the logged ego's path (the
  route's centre line) at an IDM speed for the first object on or near it, from the true agent
  boxes and velocities (what a map and a perfect detector would give), nuPlan's PDM-Closed idea.
* ``stop``: brakes at once and stays stopped (all waypoints at the current position): the score
  must punish a planner that never goes anywhere.
* a bundle (:class:`BundlePlanner`): ``load_planner`` + ``PlannerSession``, occupancy rendered
  at the ego's actual pose on the bundle's grid; the row ``world_model`` drives the plan checked
  against the model's own forecast (``check=True``, :mod:`renderworld.planning.checked`), the
  row ``world_model_raw`` the model's own plan.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from renderworld.constants import FUTURE_FRAMES, KEYFRAME_DT, GridSpec
from renderworld.sim.agents import rects_overlap
from renderworld.sim.closed_loop.boxes import EGO_HALF, SceneBoxes
from renderworld.sim.layout import World, ego_box_at
from renderworld.world.baselines import constant_turn_rate_trajectory, constant_velocity_trajectory

__all__ = [
    "REFERENCE_PLANNERS",
    "Observation",
    "LogReplay",
    "ConstantVelocity",
    "ConstantTurnRate",
    "RuleBased",
    "Stop",
    "BundlePlanner",
    "make_planner",
    "make_bundle_planners",
]


@dataclass
class Observation:
    """What a planner gets at a keyframe.

    Attributes:
        world: the scene (reference planners read its log, map or boxes; a bundle never does).
        t: time, seconds from the scene start.
        keyframe: keyframe index.
        pose: (x, y, yaw) actual rear-axle pose, scene frame.
        speed: m/s.
        displacements: [H-1, 2] metres, history steps in the current ego frame.
        yaws: [H] radians, history yaws in the current ego frame (last 0).
        command: ``left`` / ``right`` / ``straight`` from the route.
        occupancy: the last H frames [X, Y, Z] uint8, each in its own ego frame (oldest first),
            for planners that read occupancy; else empty.
    """

    world: World
    t: float
    keyframe: int
    pose: tuple[float, float, float]
    speed: float
    displacements: np.ndarray
    yaws: np.ndarray
    command: str
    occupancy: list = field(default_factory=list)


def _to_ego(pose, xy: np.ndarray) -> np.ndarray:
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    d = np.asarray(xy, dtype=np.float64) - np.array([x, y])
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)


class _Reference:
    name = ""
    privileged = False
    grid: GridSpec | None = None  # occupancy grid the planner reads (None: none)

    def reset(self, world: World) -> None:
        """Called once before each episode."""


class LogReplay(_Reference):
    """The logged ego's positions at +0.5 ... +3.0 s, in the actual ego frame."""

    name = "log_replay"
    privileged = True

    def plan(self, obs: Observation) -> np.ndarray:
        t = obs.t + KEYFRAME_DT * np.arange(1, FUTURE_FRAMES + 1)
        xy, _ = obs.world.ego.trajectory.pose(t)
        return _to_ego(obs.pose, xy)


class ConstantVelocity(_Reference):
    """The last history displacement repeated."""

    name = "cv"

    def plan(self, obs: Observation) -> np.ndarray:
        return constant_velocity_trajectory(np.asarray(obs.displacements, np.float64))


class ConstantTurnRate(_Reference):
    """The last displacement and heading change repeated."""

    name = "ctr"

    def plan(self, obs: Observation) -> np.ndarray:
        d = np.asarray(obs.displacements, np.float64)
        xy = np.concatenate([np.zeros((1, 2)), np.cumsum(d, 0)])
        xy -= xy[-1]
        poses = np.concatenate([xy, np.asarray(obs.yaws, np.float64)[:, None]], 1)
        return constant_turn_rate_trajectory(poses)


class Stop(_Reference):
    """Every waypoint at the current position: brake as hard as the car can and stay."""

    name = "stop"

    def plan(self, obs: Observation) -> np.ndarray:
        return np.zeros((FUTURE_FRAMES, 2))


class RuleBased(_Reference):
    """Route centre line at an IDM speed (privileged: true boxes and velocities).

    The path is the logged ego's (rear-axle) path. The desired speed is the scene's cruise
    speed, lowered ahead of curves so that the lateral acceleration stays <= ``a_lat`` (braking
    at ``b_curve`` toward them). Obstacles: every object whose box, at its current pose or
    extrapolated at constant velocity to +0.5 ... +``horizon`` s (5 s), overlaps the corridor (the
    ego box widened by ``margin`` on each side, slid along the path up to 60 m ahead), unless
    the ego, going on at its speed, will have passed that point by then; the nearest one along
    the path is the IDM leader, moving along the path at its velocity's component (never
    backwards). IDM (Treiber): ``a = a_max [1 - (v/v0)^4 - (s*/s)^2]``,
    ``s* = s0 + v T + v dv / (2 sqrt(a_max b))``, integrated at 0.1 s for 3 s.
    """

    name = "rule_based"
    privileged = True

    def __init__(
        self, a_max=1.5, b=3.0, s0=2.0, headway=1.0, a_lat=2.5, b_curve=2.0, margin=0.3, horizon=5.0
    ):
        self.a_max, self.b, self.s0, self.headway, self.horizon = a_max, b, s0, headway, horizon
        self.a_lat, self.b_curve, self.margin = a_lat, b_curve, margin
        self._boxes: SceneBoxes | None = None
        self._curv_speed = None

    def reset(self, world: World) -> None:
        self._boxes = SceneBoxes(world)
        path = world.ego.path
        kappa = np.abs(np.gradient(path.heading, path.s))
        v = float(world.spec.speed)
        self._curv_speed = np.minimum(v, np.sqrt(self.a_lat / np.maximum(kappa, 1e-6)))

    def _desired(self, path, s: float) -> float:
        ahead = path.s >= s
        reach = self._curv_speed[ahead] ** 2 + 2 * self.b_curve * (path.s[ahead] - s)
        return float(np.sqrt(reach.min())) if ahead.any() else float(self._curv_speed[-1])

    def _leader(self, world: World, t: float, s_ego: float, v: float) -> tuple | None:
        path = world.ego.path
        s = s_ego + np.arange(0.0, 60.0, 0.5)
        xy, hd = path.at(s)
        ec, ey = ego_box_at(xy, hd)
        half = EGO_HALF + np.array([0.0, self.margin])
        c, yaw = self._boxes.at(t)
        vel = self._boxes.velocity(t)
        reach = np.hypot(*half) + np.hypot(*self._boxes.half.T)
        v_pass = min(v, self._desired(path, s_ego))
        best = None
        for tau in np.arange(0.0, self.horizon + 1e-9, 0.5):
            pc = c + tau * vel
            near = np.hypot(*(pc[:, None, :] - ec[None]).transpose(2, 0, 1)) < reach[:, None]
            for i in np.flatnonzero(near.any(1)):
                j = np.flatnonzero(near[i])
                hit = rects_overlap(ec[j], ey[j], half, pc[i], yaw[i], self._boxes.half[i])
                if not hit.any():
                    continue
                k = int(j[np.argmax(hit)])
                if tau > 0 and s_ego + v_pass * tau > s[k] + 2 * EGO_HALF[0] + 2.0:
                    continue  # the ego will have passed that point when the object gets there
                along = max(float(np.cos(hd[k]) * vel[i, 0] + np.sin(hd[k]) * vel[i, 1]), 0.0)
                gap = float(s[k] - s_ego) - along * tau
                if best is None or gap < best[0]:
                    best = (max(gap, 0.05), along)
        return best

    def plan(self, obs: Observation) -> np.ndarray:
        world = obs.world
        path = world.ego.path
        (s_ego,), _ = path.project(np.array([obs.pose[:2]]))
        s_ego = float(s_ego)
        leader = self._leader(world, obs.t, s_ego, float(obs.speed))
        v, s = float(obs.speed), s_ego
        out = []
        dt = 0.1
        for i in range(int(round(FUTURE_FRAMES * KEYFRAME_DT / dt))):
            v0 = max(self._desired(path, s), 0.1)
            acc = self.a_max * (1 - (v / v0) ** 4)
            if leader is not None:
                gap = leader[0] + leader[1] * i * dt - (s - s_ego)
                dv = v - leader[1]
                s_star = self.s0 + v * self.headway + v * dv / (2 * np.sqrt(self.a_max * self.b))
                acc -= self.a_max * (max(s_star, 0.0) / max(gap, 0.05)) ** 2
            acc = max(acc, -8.0)
            v_new = max(v + acc * dt, 0.0)
            s += 0.5 * (v + v_new) * dt
            v = v_new
            if (i + 1) % int(round(KEYFRAME_DT / dt)) == 0:
                out.append(s)
        xy, _ = path.at(np.array(out))
        return _to_ego(obs.pose, xy)


def _same_grid(a: GridSpec, b: GridSpec) -> bool:
    return tuple(a.shape) == tuple(b.shape) and bool(
        np.allclose(a.range_min, b.range_min) and np.allclose(a.range_max, b.range_max)
    )


class BundlePlanner:
    """A planner bundle driving through the public API (``PlannerSession``).

    Args:
        planner: a loaded :class:`renderworld.planning.Planner` (``load_planner(path)``).
        name: the row's name in the tables.
        grid: the run's grid (None: the bundle's); a bundle on another grid is refused.
        check: drive the plan checked against the model's forecast (``check=True`` of
            :meth:`renderworld.planning.PlannerSession.plan`); False: the model's own plan.
        observer: what the planner sees through, with the
            :class:`~renderworld.sim.closed_loop.observe.OccupancyRenderer` interface (e.g. the
            cameras and Img2Occ: :class:`~renderworld.sim.closed_loop.cameras.CameraObserver`);
            None: the world's occupancy rendered at the ego's pose.
        true_movers: check against the scene's true future movers instead of the model's
            forecast (:mod:`renderworld.sim.closed_loop.oracle`): privileged, a headroom
            reference.
    """

    privileged = False

    def __init__(
        self,
        planner,
        name: str = "world_model",
        grid: GridSpec | None = None,
        check: bool = True,
        observer=None,
        true_movers: bool = False,
    ):
        from renderworld.planning import Planner, PlannerSession

        if not isinstance(planner, Planner):
            raise TypeError(f"planner: expected a Planner, got {type(planner).__name__}")
        if planner.grid is None:
            raise ValueError(f"planner {name}: the bundle names no occupancy grid")
        if grid is not None and not _same_grid(grid, planner.grid):
            g = planner.grid
            raise ValueError(
                f"planner {name}: the bundle's grid {g.name} {tuple(g.shape)} over "
                f"{g.range_min}..{g.range_max} differs from the run's grid {grid.name} "
                f"{tuple(grid.shape)} over {grid.range_min}..{grid.range_max}"
            )
        self.name = name
        self.planner = planner
        self.check = bool(check)
        self.observer = observer
        if true_movers and not check:
            raise ValueError(f"planner {name}: true_movers needs check=True")
        self.true_movers = bool(true_movers)
        self.privileged = self.true_movers
        self._boxes = None
        self.grid = planner.grid
        self._session = PlannerSession(planner)
        self._pushed = -1
        #: None, or a list each plan's ``(t, PlanResult)`` is appended to
        #: (:mod:`renderworld.sim.closed_loop.trace`).
        self.results: list | None = None

    def reset(self, world: World) -> None:
        self._session.reset()
        self._pushed = -1
        self._boxes = SceneBoxes(world) if self.true_movers else None

    def plan(self, obs: Observation) -> np.ndarray:
        frames = obs.occupancy
        first = obs.keyframe - len(frames) + 1
        for i, occ in enumerate(frames):
            if first + i > self._pushed:
                self._session.push(occ)
                self._pushed = first + i
        movers = None
        if self.true_movers:
            from renderworld.planning.scene import model_forecaster
            from renderworld.sim.closed_loop.oracle import true_mover_forecaster

            fallback = model_forecaster(self.planner.world_model)
            movers = true_mover_forecaster(self._boxes, obs.t, obs.pose, fallback)
        result = self._session.plan(
            obs.displacements, obs.command, forecast=False, ego_yaws=np.asarray(obs.yaws),
            check=self.check, movers=movers,
        )  # fmt: skip
        if self.results is not None:
            self.results.append((float(obs.t), result))
        return np.asarray(result.trajectory, dtype=np.float64)


REFERENCE_PLANNERS = {
    "log_replay": LogReplay,
    "cv": ConstantVelocity,
    "ctr": ConstantTurnRate,
    "rule_based": RuleBased,
    "stop": Stop,
}


def make_bundle_planners(
    path, grid: GridSpec | None = None, name: str = "world_model", true_movers: bool = False
) -> list[BundlePlanner]:
    """The rows of a planner bundle: ``<name>`` (the checked plan) and ``<name>_raw`` (the
    model's own plan), sharing one loaded bundle; with ``true_movers`` also
    ``<name>_true_movers`` (the checked plan against the scene's true future movers:
    privileged, the headroom of a better mover forecast).

    Raises:
        ValueError: naming ``planner`` when the path is not a ``*.pt`` file.
    """
    from pathlib import Path

    from renderworld.planning import load_planner

    path = Path(path)
    if path.suffix != ".pt":
        raise ValueError(f"planner: expected a planner bundle path (*.pt), got {str(path)!r}")
    bundle = load_planner(path)
    rows = [
        BundlePlanner(bundle, name=name, grid=grid, check=True),
        BundlePlanner(bundle, name=f"{name}_raw", grid=grid, check=False),
    ]
    if true_movers:
        rows.append(BundlePlanner(bundle, f"{name}_true_movers", grid, True, true_movers=True))
    return rows


def make_planner(name: str, grid: GridSpec | None = None):
    """A reference planner by name, or a bundle's checked planner from a ``planner.pt`` path
    (:func:`make_bundle_planners` gives both of its rows)."""
    if name in REFERENCE_PLANNERS:
        return REFERENCE_PLANNERS[name]()
    if not str(name).endswith(".pt"):
        raise ValueError(
            f"planners: expected one of {sorted(REFERENCE_PLANNERS)} or a planner bundle path "
            f"(*.pt), got {name!r}"
        )
    return make_bundle_planners(name, grid)[0]
