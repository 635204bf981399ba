"""Planner API: ``load_planner(path).plan(PlanRequest(...)) -> PlanResult``.

``plan(request, check=True)`` checks the model's plan against its own forecast and returns the
best candidate around it (:mod:`renderworld.planning.checked`). Streaming (one encode per new
frame): ``PlannerSession(planner)``; in a planning loop,
``retain_freed_memory()`` once per process (glibc) saves the allocator's page faults. Light to
import: torch and numpy only (no Hydra, no Open3D). Frames and units are in
:mod:`renderworld.planning.request`.
"""

from renderworld.planning.api import Planner
from renderworld.planning.bundle import (
    BUNDLE_SCHEMA_VERSION,
    BUNDLE_STAGE,
    load_planner,
    register_tokenizer,
    registered_tokenizers,
    save_planner_bundle,
)
from renderworld.planning.candidates import CheckConfig, check_config
from renderworld.planning.check import CandidateScores
from renderworld.planning.checked import CheckedPlan, check_plan
from renderworld.planning.memory import retain_freed_memory
from renderworld.planning.request import MAX_STEP_DISPLACEMENT_M, PlanRequest, PlanResult
from renderworld.planning.session import PlannerSession

__all__ = [
    "BUNDLE_SCHEMA_VERSION",
    "BUNDLE_STAGE",
    "CandidateScores",
    "CheckConfig",
    "CheckedPlan",
    "MAX_STEP_DISPLACEMENT_M",
    "PlanRequest",
    "PlanResult",
    "Planner",
    "PlannerSession",
    "check_config",
    "check_plan",
    "load_planner",
    "register_tokenizer",
    "registered_tokenizers",
    "retain_freed_memory",
    "save_planner_bundle",
]
