"""The ego's kinematic model in closed loop: :mod:`renderworld.planning.kinematics`.

The simulator drives the ego with the same model the planner tracks its candidates with, so it
lives with the planner (which must import without the simulator); the names are re-exported
here for the closed loop.
"""

from renderworld.planning.kinematics import (
    SIM_DT,
    STEPS_PER_KEYFRAME,
    EgoState,
    KinematicLimits,
    reference,
    track_plan,
)

__all__ = ["SIM_DT", "STEPS_PER_KEYFRAME", "EgoState", "KinematicLimits", "reference", "track_plan"]
