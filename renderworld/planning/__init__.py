"""Planner API: ``load_planner(path).plan(PlanRequest(...)) -> PlanResult``.

Light to import: torch and numpy only (no Hydra, no Open3D). Frames and units are in
:mod:`renderworld.planning.api`.
"""

from renderworld.planning.api import Planner, PlanRequest, PlanResult
from renderworld.planning.bundle import (
    BUNDLE_SCHEMA_VERSION,
    BUNDLE_STAGE,
    load_planner,
    register_tokenizer,
    registered_tokenizers,
    save_planner_bundle,
)

__all__ = [
    "BUNDLE_SCHEMA_VERSION",
    "BUNDLE_STAGE",
    "PlanRequest",
    "PlanResult",
    "Planner",
    "load_planner",
    "register_tokenizer",
    "registered_tokenizers",
    "save_planner_bundle",
]
