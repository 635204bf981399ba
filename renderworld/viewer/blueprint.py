"""The recording's default layout: 3-D views (scene, each model) beside the six cameras."""

from __future__ import annotations

from renderworld.constants import CAMERA_NAMES, FUTURE_FRAMES, KEYFRAME_DT

__all__ = ["scene_blueprint", "forecast_entity"]


def forecast_entity(step: int) -> str:
    """Entity of the forecast ``step`` keyframes ahead (1-based): ``world/forecast/<s>s``."""
    return f"world/forecast/{step * KEYFRAME_DT:.1f}s"


# Entities each model view shows besides its own (the ego box and agents give it context).
_CONTEXT = ["+ /world/ego/box", "+ /world/agents"]


def scene_blueprint(
    rrb,
    model_views: list[str],
    follow_ego: bool = True,
    first: str = "data",
    forecast_shown: int = FUTURE_FRAMES,
):
    """A ``rrb.Blueprint``: tabs of 3-D views (the data, then one per model layer present)
    next to a grid of the six camera images.

    Args:
        rrb: the ``rerun.blueprint`` module.
        model_views: model layers written (``"img2occ"``, ``"tokenizer"``, ``"forecast"``).
        follow_ego: the 3-D views' eye follows ``world/ego`` (from behind, above).
        first: the tab shown first: ``"data"`` or one of ``model_views``.
        forecast_shown: the forecast (steps ahead) visible at first in the forecast tab; the
            other horizons are listed there, hidden (overlaid, six volumes hide each other).

    Raises:
        ValueError: ``first`` is neither ``"data"`` nor a written model layer.
    """
    if first != "data" and first not in model_views:
        raise ValueError(f"first_view: expected 'data' or one of {model_views}, got {first!r}")
    eye = rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital,
        position=[-38.0, -30.0, 48.0],
        look_target=[6.0, 0.0, 0.0],
        eye_up=[0.0, 0.0, 1.0],
        tracking_entity="/world/ego" if follow_ego else None,
    )
    model_content = {
        "img2occ": ["+ /world/ego/img2occ/**"],
        "tokenizer": ["+ /world/ego/tokenizer/**"],
        "forecast": ["+ /world/forecast/**", "+ /world/ego/plan/**"],
    }
    titles = {
        "img2occ": "Img2Occ (Gaussians, occupancy)",
        "tokenizer": "tokenizer reconstruction",
        "forecast": "forecast and plan",
    }
    views = [
        rrb.Spatial3DView(
            name="scene (data)",
            origin="/world",
            contents=[
                "+ /world/**",
                "- /world/ego/img2occ/**",
                "- /world/ego/tokenizer/**",
                "- /world/forecast/**",
                "- /world/ego/plan/**",
            ],
            eye_controls=eye,
        )  # fmt: skip
    ]
    hidden = {
        forecast_entity(k): rrb.EntityBehavior(visible=False)
        for k in range(1, FUTURE_FRAMES + 1)
        if k != forecast_shown
    }
    for name in model_views:
        views.append(
            rrb.Spatial3DView(
                name=titles[name],
                origin="/world",
                contents=[*model_content[name], *_CONTEXT],
                eye_controls=eye,
                overrides=hidden if name == "forecast" else None,
            )
        )
    cameras = rrb.Grid(
        *[rrb.Spatial2DView(name=c, origin=f"/world/ego/cameras/{c}") for c in CAMERA_NAMES],
        grid_columns=2,
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(*views, active_tab=0 if first == "data" else 1 + model_views.index(first)),
            cameras,
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed"),
    )
