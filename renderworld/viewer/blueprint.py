"""The recording's default layout: 3-D views (scene, each model) beside the six cameras."""

from __future__ import annotations

from renderworld.constants import CAMERA_NAMES

__all__ = ["scene_blueprint"]

# Entities each model view shows besides its own (the ego box and agents give it context).
_CONTEXT = ["+ /world/ego/box", "+ /world/agents"]


def scene_blueprint(rrb, model_views: list[str], follow_ego: bool = True, first: str = "data"):
    """A ``rrb.Blueprint``: tabs of 3-D views (the data, then one per model layer present)
    next to a grid of the six camera images.

    Args:
        rrb: the ``rerun.blueprint`` module.
        model_views: model layers written (``"img2occ"``, ``"tokenizer"``, ``"forecast"``).
        follow_ego: the 3-D views' eye follows ``world/ego`` (from behind, above).
        first: the tab shown first: ``"data"`` or one of ``model_views``.

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
    for name in model_views:
        views.append(
            rrb.Spatial3DView(
                name=titles[name],
                origin="/world",
                contents=[*model_content[name], *_CONTEXT],
                eye_controls=eye,
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
