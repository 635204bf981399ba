"""One closed-loop episode: the planner drives the ego through a generated scene.

The episode starts from the logged ego state after the history (keyframe ``H - 1``, 2.0 s for
five history frames; ``nudge_m`` further along its heading where asked): the history frames are
the logged ego's. Then, at every keyframe until
the scene's last: the planner gets an :class:`~renderworld.sim.closed_loop.planners.Observation`
(occupancy rendered at the ego's actual poses if it reads occupancy, history in the current
ego frame, the route's command), its plan is checked (shape [S, 2], S >= 1 waypoints 0.5 s
apart, finite, each step at most :data:`renderworld.planning.MAX_STEP_DISPLACEMENT_M`) and
tracked for 0.5 s at 10 Hz by the kinematic model (:mod:`renderworld.sim.closed_loop.kinematics`).
Agents replay their scripted trajectories (non-reactive). After every 0.1 s step the ego box
is checked against every object's box (:func:`~renderworld.sim.closed_loop.boxes.contacts_at`)
and against the driveable surface.

A contact the ego is not at fault for (it stood still, it was hit from behind, or it was hit on
its flank while inside one lane: :mod:`renderworld.sim.closed_loop.contacts`) is recorded in
:attr:`Episode.not_at_fault_contacts` and the episode goes on; that object is then ignored, as
NAVSIM does (non-reactive agents drive on through the ego).

Ends: ``scene_end`` (the scene's last keyframe), ``collision`` (a contact the ego is at fault
for: NC 0 with an agent, 0.5 with a static object), ``off_road`` (a corner or edge midpoint of
the ego box off the driveable surface), or ``planner_error`` (a plan of the wrong shape,
NaN/inf, or an impossible step: the episode is a failure, the reason kept).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from renderworld.constants import HISTORY_FRAMES, KEYFRAME_DT
from renderworld.planning.request import MAX_STEP_DISPLACEMENT_M
from renderworld.sim.closed_loop.boxes import Contact, SceneBoxes, contacts_at, ego_on_road
from renderworld.sim.closed_loop.kinematics import (
    SIM_DT,
    STEPS_PER_KEYFRAME,
    EgoState,
    KinematicLimits,
    track_plan,
)
from renderworld.sim.closed_loop.observe import (
    OccupancyRenderer,
    history_inputs,
    pose_matrix_2d,
    route_command,
)
from renderworld.sim.closed_loop.planners import Observation
from renderworld.sim.layout import World

__all__ = ["END_REASONS", "Episode", "run_episode"]

END_REASONS = ("scene_end", "collision", "off_road", "planner_error")


@dataclass
class Episode:
    """What happened in one episode.

    Attributes:
        scene: scene name.
        behaviour: the scene's behaviour.
        planner: the planner's name.
        times: [N] seconds of the 10 Hz states (the first is the start).
        states: [N, 4] (x, y, yaw, speed), scene frame, rear axle.
        end: one of :data:`END_REASONS`.
        reason: a sentence for ``planner_error`` (what the planner returned), else "".
        contact: the at-fault contact that ended the episode (``collision``), else None.
        not_at_fault_contacts: the contacts the ego was not at fault for, in time order (at
            most one per object; the episode went on after each).
        commands: the command at each plan.
        voxelise_ms: per rendered occupancy frame, milliseconds.
        plan_ms: per plan, milliseconds.
        saturated: 10 Hz steps at which the plan asked more than the car's limits.
    """

    scene: str
    behaviour: str
    planner: str
    times: np.ndarray
    states: np.ndarray
    end: str
    reason: str = ""
    contact: Contact | None = None
    not_at_fault_contacts: list = field(default_factory=list)
    commands: list = field(default_factory=list)
    voxelise_ms: list = field(default_factory=list)
    plan_ms: list = field(default_factory=list)
    saturated: int = 0


def scene_keyframes(world: World) -> int:
    """Keyframes of a scene (2 Hz, ``duration / 0.5 + 1``)."""
    return int(round(world.duration / KEYFRAME_DT)) + 1


def _check_plan(traj) -> tuple[np.ndarray | None, str]:
    try:
        arr = np.asarray(traj, dtype=np.float64)
    except (TypeError, ValueError):
        return None, f"plan: expected an [S, 2] array, got {type(traj).__name__}"
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] != 2:
        return None, f"plan: expected shape [S >= 1, 2], got {list(arr.shape)}"
    if not np.isfinite(arr).all():
        return None, "plan: NaN or inf in the trajectory"
    steps = np.hypot(*np.diff(np.concatenate([np.zeros((1, 2)), arr]), axis=0).T)
    worst = int(steps.argmax())
    if steps[worst] > MAX_STEP_DISPLACEMENT_M:
        return None, (
            f"plan: impossible step of {steps[worst]:.3g} m in {KEYFRAME_DT:g} s at waypoint "
            f"{worst} (at most {MAX_STEP_DISPLACEMENT_M:g} m)"
        )
    return arr, ""


def run_episode(
    world: World,
    planner,
    limits: KinematicLimits | None = None,
    renderer: OccupancyRenderer | None = None,
    boxes: SceneBoxes | None = None,
    nudge_m: float = 0.0,
) -> Episode:
    """Drive ``planner`` through ``world`` (module docstring: the loop and how it ends).

    Args:
        world: a generated scene (:func:`renderworld.sim.build_world`).
        planner: an object with ``name``, ``grid`` (None or the occupancy grid it reads),
            ``reset(world)`` and ``plan(Observation) -> [6, 2]``.
        limits: the car's limits (default :class:`KinematicLimits`).
        renderer: occupancy renderer on ``planner.grid`` (None: the planner's ``observer`` if
            it has one, else made here when needed).
        boxes: the world's boxes (made here when None).
        nudge_m: the ego starts this many metres further along its heading than the log (the
            last history frame is seen from there too): a perturbation far below anything a
            planner should answer, which shows how far the loop's own chaos moves a score.

    Raises:
        ValueError: naming the scene when it is too short for the history and one plan, or
            ``nudge_m`` when it is not finite.
    """
    limits = limits or KinematicLimits()
    if not np.isfinite(nudge_m):
        raise ValueError(f"nudge_m: expected a finite distance in metres, got {nudge_m}")
    n_kf = scene_keyframes(world)
    h = HISTORY_FRAMES
    if n_kf < h + 1:
        raise ValueError(
            f"scene {world.name}: {n_kf} keyframes, expected at least {h + 1} ({h} history "
            "frames and one step to drive)"
        )
    grid = getattr(planner, "grid", None)
    renderer = renderer or getattr(planner, "observer", None)
    if grid is not None and (renderer is None or renderer.grid != grid):
        renderer = OccupancyRenderer(grid)
    boxes = boxes or SceneBoxes(world)
    planner.reset(world)
    k0 = h - 1
    traj = world.ego.trajectory
    hist = [np.array([*traj.pose(k * KEYFRAME_DT)[0], traj.pose(k * KEYFRAME_DT)[1]])
            for k in range(h)]  # fmt: skip
    hist[-1][:2] += nudge_m * np.array([np.cos(hist[-1][2]), np.sin(hist[-1][2])])
    t0 = k0 * KEYFRAME_DT
    x, y, yaw = hist[-1]
    state = EgoState(float(x), float(y), float(yaw), traj.speed(t0))
    ep = Episode(world.name, world.spec.behaviour, planner.name, np.zeros(0), np.zeros((0, 4)),
                 "scene_end")  # fmt: skip
    frames, cleared = [], set()
    if grid is not None:
        for k, p in enumerate(hist):
            c = time.perf_counter()
            frames.append(renderer.render(world, k * KEYFRAME_DT, pose_matrix_2d(*p)))
            ep.voxelise_ms.append(1e3 * (time.perf_counter() - c))
    times, states = [t0], [(state.x, state.y, state.yaw, state.speed)]
    for k in range(k0, n_kf - 1):
        t = k * KEYFRAME_DT
        disp, yaws = history_inputs(np.stack(hist[-h:]))
        cmd = route_command(world, state.x, state.y, state.yaw)
        ep.commands.append(cmd)
        obs = Observation(world, t, k, (state.x, state.y, state.yaw), state.speed, disp, yaws,
                          cmd, frames[-h:])  # fmt: skip
        c = time.perf_counter()
        plan, why = _check_plan(planner.plan(obs))
        ep.plan_ms.append(1e3 * (time.perf_counter() - c))
        if plan is None:
            ep.end, ep.reason = "planner_error", why
            break
        cy, sy = np.cos(state.yaw), np.sin(state.yaw)
        scene_xy = np.stack([state.x + cy * plan[:, 0] - sy * plan[:, 1],
                             state.y + sy * plan[:, 0] + cy * plan[:, 1]], -1)  # fmt: skip
        new_states, sat = track_plan(state, scene_xy, limits, STEPS_PER_KEYFRAME)
        ep.saturated += sat
        stop = False
        for j, st in enumerate(new_states):
            tj = t + (j + 1) * SIM_DT
            times.append(tj)
            states.append((st.x, st.y, st.yaw, st.speed))
            state = st
            hits = contacts_at(boxes, tj, st.x, st.y, st.yaw, st.speed, cleared)
            for hit in hits:
                if not hit.at_fault:
                    ep.not_at_fault_contacts.append(hit)
                    cleared.add(hit.key)
            fault = [hit for hit in hits if hit.at_fault]
            if fault:  # an agent (NC 0) before a static object (NC 0.5), then world order
                worst = min(fault, key=lambda f: not f.agent)
                ep.end, ep.contact, stop = "collision", worst, True
                break
            if not ego_on_road(world, st.x, st.y, st.yaw):
                ep.end, stop = "off_road", True
                break
        if stop:
            break
        hist.append(np.array([state.x, state.y, state.yaw]))
        if grid is not None:
            c = time.perf_counter()
            frames.append(renderer.render(world, (k + 1) * KEYFRAME_DT, pose_matrix_2d(*hist[-1])))
            ep.voxelise_ms.append(1e3 * (time.perf_counter() - c))
            frames = frames[-h:]
    ep.times = np.round(np.asarray(times), 9)
    ep.states = np.asarray(states, dtype=np.float64)
    return ep
