"""World models of the ``world_model`` stage built from configs and checkpoints (a mixin).

When evaluating, the architecture and forecaster are the checkpoint's; a Camera-setting model
(``camera_ckpt``) is loaded strictly and checked against its own tokenizer. Needs the stage's
``settings``, ``forecaster``, ``eval_settings``, ``setting_models``, ``tokenizer`` and
``tokenizer_of`` (declared on the class).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import fields
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf
from torch import nn

from renderworld.training.checkpoint import CheckpointError, load_checkpoint
from renderworld.training.stages.common import evaluated_checkpoint
from renderworld.training.stages.world_model.settings import (
    EvalSetting,
    build_world_model,
    check_same_tokenizer,
    forecaster_of,
    world_model_config,
)
from renderworld.world import (
    WorldModel,
    WorldModelConfig,
)
from renderworld.world.forecast import check_movers

if TYPE_CHECKING:
    from renderworld.tokenizer import SceneTokenizer
    from renderworld.training.stages.world_model.settings import StageSettings

__all__ = ["CheckpointModels", "with_movers"]


def with_movers(model: nn.Module, cfg: Any) -> nn.Module:
    """``model`` with the run's ``stage.movers`` when the command line sets one (evaluating a
    checkpoint: how the forecast moves others is no weight, so any pose-warp checkpoint can be
    scored either way); unchanged when it is null (the checkpoint's own)."""
    movers = cfg.stage.get("movers")
    if movers is not None and hasattr(model, "movers"):
        model.movers = check_movers(str(movers), "stage.movers")
    return model


class CheckpointModels:
    """``build_model`` and the checkpoint checks of the world-model stage."""

    # What the class this is mixed into provides (its ``__init__``, ``FrozenTokenizers``):
    settings: StageSettings  # validated ``stage.*`` keys (``tokenizer_ckpt``)
    forecaster: str  # "tokens" or "pose_warp"; ``build_model`` sets the checkpoint's own
    eval_settings: list[EvalSetting]  # the evaluated settings (3D-Occ, Camera)
    setting_models: dict[str, nn.Module]  # a setting's own model by key (filled here)
    tokenizer: SceneTokenizer  # the run's frozen tokenizer (``stage.tokenizer_ckpt``)
    tokenizer_of: Callable[[str | None], SceneTokenizer]  # frozen tokenizer of a checkpoint

    def build_model(self, cfg: Any) -> nn.Module:
        """The world model; when evaluating (``ckpt`` set) its architecture is the checkpoint's.

        ``stage.model`` keys that differ from the checkpoint's are taken from it with a warning
        (they are architecture only); a different ``stage.history`` / ``stage.future`` is an
        error (they define the evaluation protocol and the model's window).
        """
        mine = world_model_config(cfg, self.tokenizer.cfg)
        ckpt = evaluated_checkpoint(cfg)
        if ckpt is None:
            return build_world_model(self.forecaster, mine, cfg)
        stored = load_checkpoint(ckpt, expected_stage="world_model")["config"]
        self.forecaster = forecaster_of(OmegaConf.create(stored))
        model = self._model_of_checkpoint(ckpt, mine, "ckpt")
        model = with_movers(model, cfg)
        for s in self.eval_settings:
            if s.ckpt:  # the Camera setting's own model (camera_ckpt), loaded strictly
                self.setting_models[s.key] = self._load_setting_model(s, cfg)
            elif s.tokenizer:  # the ckpt model on the setting's own tokenizer's codes
                self._check_tokenizer_fits(model.config, s, "ckpt")
                stored = OmegaConf.create(
                    load_checkpoint(ckpt, expected_stage="world_model")["config"]
                )
                check_same_tokenizer(stored, s.tokenizer, "camera_tokenizer_ckpt")
        return model

    def _check_tokenizer_fits(self, wm: WorldModelConfig, s: EvalSetting, what: str) -> None:
        """ValueError when setting ``s``'s tokenizer does not give the codes model ``wm`` reads."""
        tc = self.tokenizer_of(s.tokenizer).cfg
        got = (tuple(tc.codebook_sizes), tuple(tc.latent_shape))
        want = (tuple(wm.codebook_sizes), tuple(wm.token_grid))
        if got != want:
            raise ValueError(
                f"camera_tokenizer_ckpt: {s.tokenizer!r} has codebooks {got[0]} on a {got[1]} "
                f"latent grid, the {what} world model reads {want[0]} on {want[1]}"
            )

    def _load_setting_model(self, s: EvalSetting, cfg: Any) -> nn.Module:
        from renderworld.training.checkpoint import check_state_dict_keys

        ckpt = str(s.ckpt)
        mine = world_model_config(cfg, self.tokenizer_of(s.tokenizer).cfg)
        model = with_movers(self._model_of_checkpoint(ckpt, mine, "camera_ckpt", s.tokenizer), cfg)
        state = load_checkpoint(ckpt, expected_stage="world_model")["model"]
        check_state_dict_keys(model, state, source=f"camera_ckpt {ckpt!r}")
        model.load_state_dict(state, strict=True)
        return model.eval()

    def _model_of_checkpoint(
        self, ckpt: Any, mine: WorldModelConfig, what: str, tokenizer: str | None = None
    ) -> WorldModel:
        """A world model with the architecture stored in ``ckpt`` (checked against ``mine``).

        ``tokenizer``: checkpoint of the tokenizer it runs on (None = ``stage.tokenizer_ckpt``);
        a warning when the model was trained on another file.
        """
        try:
            stored = load_checkpoint(ckpt, expected_stage="world_model")["config"]
        except CheckpointError as err:
            raise CheckpointError(f"{what}: {err}") from err
        stored = OmegaConf.create(stored)
        if tokenizer is None:
            check_same_tokenizer(stored, self.settings.tokenizer_ckpt)
        else:
            check_same_tokenizer(stored, tokenizer, "camera_tokenizer_ckpt")
        theirs = world_model_config(stored, self.tokenizer_of(tokenizer).cfg)
        diff = [
            f.name
            for f in fields(WorldModelConfig)
            if getattr(mine, f.name) != getattr(theirs, f.name)
        ]
        for key, name in (("history_frames", "history"), ("future_frames", "future")):
            if key in diff:
                raise ValueError(
                    f"stage.{name}: the checkpoint {str(ckpt)!r} ({what}) was trained with "
                    f"{getattr(theirs, key)}, this run has {getattr(mine, key)}; pass "
                    f"stage.{name}={getattr(theirs, key)}"
                )
        if diff:
            warnings.warn(
                "stage.model: "
                + ", ".join(f"{k}={getattr(theirs, k)} (not {getattr(mine, k)})" for k in diff)
                + f" taken from the checkpoint {str(ckpt)!r}",
                UserWarning,
                stacklevel=2,
            )
        kind = forecaster_of(stored)
        if kind != self.forecaster:
            raise ValueError(
                f"{what}: {str(ckpt)!r} is a stage.forecaster={kind!r} model, the evaluated "
                f"model is {self.forecaster!r}; both settings need the same forecaster"
            )
        return build_world_model(kind, theirs, stored)
