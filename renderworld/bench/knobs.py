"""What the sweep can change (knobs per stage), what it measures (metrics per stage), and how a
knob value becomes a command-line override.

Training stages (``img2occ``, ``tokenizer``, ``world_model``) take Hydra overrides of their
experiment; the ``planner`` stage takes options of :class:`renderworld.planning.Planner` and of
the timed call (``renderworld.bench.planner_latency``), written ``key=value`` the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["KNOBS", "STAGE_METRICS", "DEFAULT", "TRAINED_STAGES", "Knob", "format_value",
           "knob_override"]  # fmt: skip

DEFAULT = "default"


@dataclass(frozen=True)
class Knob:
    """A swept setting: the key it overrides and how a value is written there.

    ``kind``: ``"name"`` (a config-group option), ``"str"``, ``"bool"``, ``"int"``,
    ``"float"``, ``"size"`` ([h, w]) or ``"library"`` (true: the bench's scenario library in
    ``stage.extra_train_roots``, false: none).
    """

    key: str
    kind: str
    what: str


#: Knobs per stage (name -> Knob). A preset naming another knob is an error.
KNOBS: dict[str, dict[str, Knob]] = {
    "img2occ": {
        "grid": Knob("grid", "name", "voxel grid (Occ3D range): coarse, quarter, half"),
        "input_size": Knob("stage.input_size", "size", "network input [H, W] of the 6 images"),
        "render_size": Knob("stage.render_size", "size", "rendered / label maps [H, W]"),
        "views_per_step": Knob("stage.model.views_per_step", "int", "cameras rendered per step"),
        "prune_opacity": Knob(
            "stage.model.prune_opacity", "float", "skip Gaussians below this opacity (0: off)"
        ),
        "fine_semantics": Knob(
            "stage.model.fine_semantics", "bool", "stride-2 per-pixel class head (on/off)"
        ),
        "feature_stride": Knob("stage.model.feature_stride", "int", "lifted feature stride"),
        "backproject_weight": Knob(
            "stage.model.backproject_weight", "float", "back-projected voxel targets (0: off)"
        ),
    },
    "tokenizer": {
        "latent_size": Knob("stage.model.latent_shape", "size", "token grid [h, w]"),
        "latent_channels": Knob("stage.model.latent_channels", "int", "latent channels"),
        "codebook_size": Knob("stage.model.codebook_size", "int", "codebook entries K"),
    },
    "world_model": {
        "forecaster": Knob("stage.forecaster", "str", "tokens or pose_warp (pose-aware)"),
        "history": Knob("stage.history", "int", "input frames (0.5 s apart)"),
        "width": Knob("stage.model.embed_dim", "int", "transformer width D"),
        "steps": Knob("trainer.max_steps", "int", "training steps (the budget's, overridden)"),
        "scenario_library": Knob(
            "stage.extra_train_roots", "library", "the scenario library's windows (on/off)"
        ),
    },
    "planner": {
        "forecast": Knob(
            "forecast", "bool", "decode the 3 s occupancy forecast (false: trajectory only)"
        ),  # fmt: skip
        "precision": Knob("precision", "str", "decoder precision: float32 or bfloat16"),
        "threads": Knob("threads", "int", "torch intra-op threads"),
        "check": Knob(
            "check", "bool", "the plan checked against the model's forecast (false: raw plan)"
        ),
        "grid": Knob(
            "grid",
            "str",
            "mini (the main job's 50x50x4 models), occ3d (200x200x16, paper-sized untrained "
            "pose-warp models: latency only) or occ3d-checked (the same, checked plan)",
        ),  # fmt: skip
    },
}
TRAINED_STAGES = ("img2occ", "tokenizer", "world_model")

#: Per stage: (primary metric, higher is better, label), (secondary metric, higher is better,
#: label), what one inference sample is.
STAGE_METRICS: dict[str, dict[str, Any]] = {
    "img2occ": {
        "metric": ("val/cam/miou", True, "mIoU, camera mask (%)"),
        "metric2": ("val/cam/iou", True, "IoU, camera mask (%)"),
        "sample": "one 6-camera keyframe -> occupancy (forward + readout)",
    },
    "tokenizer": {
        "metric": ("val/miou", True, "recon. mIoU (%)"),
        "metric2": ("val/iou", True, "recon. IoU (%)"),
        "sample": "one occupancy frame -> codes -> occupancy (encode + decode)",
    },
    "world_model": {
        "metric": ("val/model/miou_avg", True, "forecast mIoU, mean 1-3 s (%)"),
        "metric2": ("val/model/l2_at_horizon_3s", False, "L2 @ 3 s (m)"),
        "heldout": ("heldout/val/model/miou_avg", "held-out fixture: forecast mIoU (%)"),
        "sample": "one plan through renderworld.planning (PlannerSession: push the new frame, "
        "roll out and decode 3 s)",
    },
    "planner": {
        "metric": ("val/l2_3s", False, "plan L2 @ 3 s, mini_val (m)"),
        "metric2": ("val/forecast_equal", True, "forecast voxels equal to float32's (%)"),
        "sample": "one plan: PlannerSession.push(new frame) + plan(), batch 1",
    },
}

_KIND_TEXT = {
    "name": "a config option name (str)",
    "str": "a string",
    "bool": "true or false",
    "int": "an int",
    "float": "a number",
    "size": "a pair of positive ints [h, w]",
    "library": "true or false",
}


def format_value(value: Any) -> str:
    """A knob value as text: ``[96, 176]`` -> ``96x176``, ``0.0`` -> ``0``."""
    if isinstance(value, (list, tuple)):
        return "x".join(format_value(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def knob_override(knob: Knob, name: str, value: Any, where: str, library: str | None) -> str:
    """``key=value`` of one knob value.

    Args:
        knob: the knob. name: its name (messages). value: as written in the preset.
        where: the preset key (messages). library: the scenario library's folder (``library``
            knobs; None: none configured).

    Raises:
        TypeError: a value of the wrong type for the knob's kind.
        ValueError: a ``library`` knob set to true without a library folder.
    """
    bad = TypeError(f"{where}: expected {_KIND_TEXT[knob.kind]} for knob {name!r}, got {value!r}")
    if knob.kind in ("name", "str"):
        if not isinstance(value, str) or not value:
            raise bad
        return f"{knob.key}={value}"
    if knob.kind in ("bool", "library"):
        if not isinstance(value, bool):
            raise bad
        if knob.kind == "bool":
            return f"{knob.key}={str(value).lower()}"
        if not value:
            return f"{knob.key}=[]"
        if not library:
            raise ValueError(
                f"{where}: {name}=true needs the bench key scenario_library (a folder)"
            )
        return f"{knob.key}=[{library}]"
    if knob.kind == "int":
        if not isinstance(value, int) or isinstance(value, bool):
            raise bad
        return f"{knob.key}={value}"
    if knob.kind == "float":
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise bad
        return f"{knob.key}={float(value)!r}"
    ok = (
        isinstance(value, (list, tuple))
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
    )
    if not ok:
        raise bad
    return f"{knob.key}=[{int(value[0])},{int(value[1])}]"
