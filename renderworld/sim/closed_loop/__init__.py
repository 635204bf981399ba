"""Closed-loop driving in the simulator: a planner drives, the scene answers, scores say how.

A planner (a reference planner or any planner bundle) drives the ego through generated scenes:
every 0.5 s it plans from what it observes at the ego's **actual** pose (occupancy on its grid,
history, the route's command), a kinematic model tracks the plan at 10 Hz, the scripted agents
replay their trajectories (non-reactive), and the episode ends at the scene's end, a collision
the ego is at fault for (``contacts``) or leaving the road. Scores follow NAVSIM's PDM score
(``scores``, ``comfort``). ``tools/drive.py`` runs it; docs/closed_loop.md explains it.
"""

from renderworld.planning.comfort import comfort_signals, comfort_violations, comfort_windows
from renderworld.sim.closed_loop.boxes import Contact, SceneBoxes, contacts_at
from renderworld.sim.closed_loop.contacts import LaneMap, contact_at_fault, contact_kind, is_agent
from renderworld.sim.closed_loop.episode import END_REASONS, Episode, run_episode
from renderworld.sim.closed_loop.kinematics import SIM_DT, EgoState, KinematicLimits, track_plan
from renderworld.sim.closed_loop.observe import OccupancyRenderer, history_inputs, route_command
from renderworld.sim.closed_loop.planners import (
    REFERENCE_PLANNERS,
    BundlePlanner,
    ConstantTurnRate,
    ConstantVelocity,
    LogReplay,
    Observation,
    RuleBased,
    Stop,
    make_bundle_planners,
    make_planner,
)
from renderworld.sim.closed_loop.report import summary_markdown, write_outputs
from renderworld.sim.closed_loop.runner import ClosedLoopRun, run_closed_loop, self_check
from renderworld.sim.closed_loop.scores import (
    COMFORT_BOUNDS,
    add_best_progress,
    aggregate,
    pdms,
    score_episode,
)

__all__ = [
    "COMFORT_BOUNDS",
    "END_REASONS",
    "REFERENCE_PLANNERS",
    "SIM_DT",
    "BundlePlanner",
    "ClosedLoopRun",
    "ConstantTurnRate",
    "ConstantVelocity",
    "Contact",
    "EgoState",
    "Episode",
    "KinematicLimits",
    "LaneMap",
    "LogReplay",
    "Observation",
    "OccupancyRenderer",
    "RuleBased",
    "Stop",
    "SceneBoxes",
    "add_best_progress",
    "aggregate",
    "comfort_signals",
    "comfort_violations",
    "comfort_windows",
    "contact_at_fault",
    "contact_kind",
    "contacts_at",
    "history_inputs",
    "is_agent",
    "make_bundle_planners",
    "make_planner",
    "pdms",
    "route_command",
    "run_closed_loop",
    "run_episode",
    "score_episode",
    "self_check",
    "summary_markdown",
    "track_plan",
    "write_outputs",
]
