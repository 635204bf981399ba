"""The world-model stage's settings: ``stage.*`` validated, the model built from them.

:func:`stage_settings` reads and checks the stage's options (:class:`StageSettings`);
:func:`build_world_model` builds the token or pose-warp model they name; the evaluation's settings
("3D-Occ", "Camera") live in :mod:`~renderworld.training.stages.world_model.eval_settings` and are
exported here too.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from renderworld.constants import FUTURE_FRAMES
from renderworld.data.table_cache import default_cache_root
from renderworld.training.stages.world_model.eval_settings import (
    EvalSetting,
    eval_settings,
    setting_header,
)
from renderworld.world import WorldModel, WorldModelConfig
from renderworld.world.movers import MOVERS
from renderworld.world.pose import ANCHORS, PoseWarpWorldModel

__all__ = [
    "EvalSetting",
    "eval_settings",
    "setting_header",
    "world_model_config",
    "stage_settings",
    "check_same_tokenizer",
    "FORECASTER_KINDS",
    "POSE_STEP_WEIGHTINGS",
    "StageSettings",
    "build_world_model",
    "extra_train_roots",
    "forecaster_of",
    "frame_cache_dir",
]

# WorldModelConfig fields that come from the tokenizer and the stage, not from stage.model.
_DERIVED = ("codebook_sizes", "token_grid", "history_frames", "future_frames")


FORECASTER_KINDS = ("tokens", "pose_warp")
#: ``stage.pose_step_weighting`` values (see ``pose_warp.pose_step_weights``).
POSE_STEP_WEIGHTINGS = ("uniform", "inverse")


@dataclass(frozen=True)
class StageSettings:
    """Validated ``stage.*`` keys; the ``pose_*`` / ``lambda_pose`` ones drive ``pose_warp``."""

    tokenizer_ckpt: str
    history: int
    future: int
    lambda_l2: float
    cache_tokens: bool
    lambda_pose: float = 1.0
    pose_yaw_weight: float = 5.0
    pose_mirror: bool = False
    pose_anchors: str = "ctr"
    pose_step_weighting: str = "uniform"
    movers: str = "static"
    pose_kinematics: bool = False
    pose_motion_frames: int = 0
    pose_agents: int = 0
    pose_leader: bool = False
    pose_leader_stop: bool = False
    pose_heads: int = 1
    pose_bev_pool: int = 4
    pose_lr_scale: float = 1.0
    pose_warmup_steps: int = 0
    pose_joint_lr_scale: float | None = None
    pose_history_dropout: float = 0.0
    pose_history_noise_m: float = 0.0
    mover_fit_steps: int = 0
    mover_lr: float = 2e-3
    mover_batch: int = 256

    @property
    def joint_pose_lr_scale(self) -> float:
        """The pose head's rate factor after the warm-up (0: frozen): ``pose_joint_lr_scale``,
        else ``pose_lr_scale``."""
        joint = self.pose_joint_lr_scale
        return self.pose_lr_scale if joint is None else joint


def _number(s: Any, key: str, default: float) -> float:
    value = s.get(key, default)
    if value is None:
        value = default
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not value >= 0:
        raise ValueError(f"stage.{key}: expected a number >= 0, got {value!r}")
    return float(value)


def _choice(s: Any, key: str, default: str, allowed: tuple[str, ...]) -> str:
    value = s.get(key) or default
    if value not in allowed:
        raise ValueError(f"stage.{key}: expected one of {allowed}, got {value!r}")
    return str(value)


def _flag(s: Any, key: str) -> bool:
    """``stage.<key>`` as a bool (default false); anything else refused naming the key."""
    value = s.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"stage.{key}: expected true or false, got {value!r}")
    return value


def stage_settings(cfg: Any) -> StageSettings:
    """The validated ``stage.*`` keys of a world-model run config (ValueError naming the key).

    The ``pose_warp`` options are checked here too, whichever forecaster the run uses, so a bad
    value fails when the stage is built, not at the first loss.
    """
    s = cfg.stage
    history, future, lam = s.get("history"), s.get("future"), s.get("lambda_l2")
    if not isinstance(history, int) or isinstance(history, bool) or history < 2:
        raise ValueError(
            f"stage.history: expected an int >= 2 (the constant-velocity baselines need one "
            f"displacement), got {history!r}"
        )
    if not isinstance(future, int) or isinstance(future, bool) or not 1 <= future <= FUTURE_FRAMES:
        raise ValueError(f"stage.future: expected an int in 1..{FUTURE_FRAMES}, got {future!r}")
    if not isinstance(lam, (int, float)) or isinstance(lam, bool) or not lam >= 0:
        raise ValueError(f"stage.lambda_l2: expected a number >= 0, got {lam!r}")
    ckpt = s.get("tokenizer_ckpt")
    if not ckpt:
        raise ValueError(
            "stage.tokenizer_ckpt: required; pass the tokenizer run's checkpoint, e.g. "
            "stage.tokenizer_ckpt=outputs/train/tokenizer/<time>/checkpoints/best.pt"
        )
    mirror = _flag(s, "pose_mirror")
    kinematics = _flag(s, "pose_kinematics")
    motion = s.get("pose_motion_frames") or 0
    if not isinstance(motion, int) or isinstance(motion, bool) or not 0 <= motion < history:
        raise ValueError(
            f"stage.pose_motion_frames: expected an int in 0..{history - 1}, got {motion!r}"
        )
    agents = s.get("pose_agents") or 0
    if not isinstance(agents, int) or isinstance(agents, bool) or agents < 0:
        raise ValueError(f"stage.pose_agents: expected an int >= 0, got {agents!r}")
    leader = _flag(s, "pose_leader")
    leader_stop = _flag(s, "pose_leader_stop")
    heads = s.get("pose_heads", 1)
    heads = 1 if heads is None else heads
    if not isinstance(heads, int) or isinstance(heads, bool) or heads < 1:
        raise ValueError(f"stage.pose_heads: expected an int >= 1, got {heads!r}")
    bev_pool = s.get("pose_bev_pool", 4)
    bev_pool = 4 if bev_pool is None else bev_pool
    if not isinstance(bev_pool, int) or isinstance(bev_pool, bool) or bev_pool < 1:
        raise ValueError(f"stage.pose_bev_pool: expected an int >= 1, got {bev_pool!r}")
    lr_scale = _number(s, "pose_lr_scale", 1.0)
    if lr_scale <= 0:
        raise ValueError(f"stage.pose_lr_scale: expected a number > 0, got {lr_scale!r}")
    warmup = s.get("pose_warmup_steps") or 0
    if not isinstance(warmup, int) or isinstance(warmup, bool) or warmup < 0:
        raise ValueError(f"stage.pose_warmup_steps: expected an int >= 0, got {warmup!r}")
    joint = s.get("pose_joint_lr_scale")
    if joint is not None:
        joint = _number(s, "pose_joint_lr_scale", 0.0)
        if joint == 0 and warmup == 0:
            raise ValueError(
                "stage.pose_joint_lr_scale=0 freezes the pose head in the joint training: it "
                "needs stage.pose_warmup_steps > 0 to be fitted at all"
            )
    dropout = _number(s, "pose_history_dropout", 0.0)
    if dropout > 1:
        raise ValueError(
            f"stage.pose_history_dropout: expected a fraction in [0, 1], got {dropout!r}"
        )
    noise = _number(s, "pose_history_noise_m", 0.0)
    fit = s.get("mover_fit_steps") or 0
    if not isinstance(fit, int) or isinstance(fit, bool) or fit < 0:
        raise ValueError(f"stage.mover_fit_steps: expected an int >= 0, got {fit!r}")
    movers = _choice(s, "movers", "static", MOVERS)
    if fit and movers != "learned":
        raise ValueError(
            f"stage.mover_fit_steps={fit}: fits the mover head of stage.movers=learned, "
            f"got stage.movers={movers!r}"
        )
    if movers == "learned" and not fit and cfg.get("task") != "eval":
        raise ValueError(
            "stage.movers=learned: its mover head is fitted before the joint training; set "
            "stage.mover_fit_steps > 0"
        )
    batch = s.get("mover_batch") or 256
    if not isinstance(batch, int) or isinstance(batch, bool) or batch < 1:
        raise ValueError(f"stage.mover_batch: expected an int >= 1, got {batch!r}")
    mover_lr = _number(s, "mover_lr", 2e-3)
    if mover_lr <= 0:
        raise ValueError(f"stage.mover_lr: expected a number > 0, got {mover_lr!r}")
    return StageSettings(
        str(ckpt),
        history,
        future,
        float(lam),
        bool(s.get("cache_tokens", True)),
        lambda_pose=_number(s, "lambda_pose", 1.0),
        pose_yaw_weight=_number(s, "pose_yaw_weight", 5.0),
        pose_mirror=mirror,
        pose_anchors=_choice(s, "pose_anchors", "ctr", ANCHORS),
        pose_step_weighting=_choice(s, "pose_step_weighting", "uniform", POSE_STEP_WEIGHTINGS),
        movers=movers,
        pose_kinematics=kinematics,
        pose_motion_frames=motion,
        pose_agents=agents,
        pose_leader=leader,
        pose_leader_stop=leader_stop,
        pose_heads=heads,
        pose_bev_pool=bev_pool,
        pose_lr_scale=lr_scale,
        pose_warmup_steps=warmup,
        pose_joint_lr_scale=joint,
        pose_history_dropout=dropout,
        pose_history_noise_m=noise,
        mover_fit_steps=fit,
        mover_lr=mover_lr,
        mover_batch=batch,
    )


def world_model_config(cfg: Any, tokenizer_cfg: Any) -> WorldModelConfig:
    """The :class:`WorldModelConfig` of a run config on a tokenizer.

    Args:
        cfg: run config (``stage.model`` fields, ``stage.history``, ``stage.future``).
        tokenizer_cfg: the tokenizer's ``TokenizerConfig`` (codebook sizes, latent grid).

    Raises:
        ValueError: unknown ``stage.model`` keys, or keys that the tokenizer / stage set.
    """
    st = stage_settings(cfg)
    model = OmegaConf.to_container(cfg.stage.model, resolve=True) if cfg.stage.model else {}
    known = {f.name for f in fields(WorldModelConfig)} - set(_DERIVED)
    for key in model:
        if key in _DERIVED:
            raise ValueError(
                f"stage.model.{key}: set by the tokenizer / stage.history / stage.future, "
                "remove it from stage.model"
            )
        if key not in known:
            raise ValueError(f"stage.model.{key}: unknown key; expected one of {sorted(known)}")
    return WorldModelConfig(
        codebook_sizes=tuple(tokenizer_cfg.codebook_sizes),
        token_grid=tuple(tokenizer_cfg.latent_shape),
        history_frames=st.history,
        future_frames=st.future,
        **model,
    )


def check_same_tokenizer(trained_cfg: Any, tokenizer_ckpt, key: str = "tokenizer_ckpt") -> None:
    """Warn when ``tokenizer_ckpt`` (config key ``key``) is not the file the world model was
    trained on."""
    trained_on = trained_cfg.stage.get("tokenizer_ckpt")
    if trained_on and Path(str(trained_on)).resolve() != Path(str(tokenizer_ckpt)).resolve():
        warnings.warn(
            f"{key}: {str(tokenizer_ckpt)!r} differs from the tokenizer the world "
            f"model was trained on ({trained_on!r}); results are only valid if they hold the "
            "same weights",
            UserWarning,
            stacklevel=3,
        )


def forecaster_of(cfg: Any) -> str:
    """``stage.forecaster`` of a run config (absent: ``"tokens"``, the original world model)."""
    return _choice(cfg.stage, "forecaster", "tokens", FORECASTER_KINDS)


def build_world_model(
    kind: str, config: WorldModelConfig, cfg: Any = None
) -> WorldModel | PoseWarpWorldModel:
    """:class:`WorldModel` (``"tokens"``) or :class:`PoseWarpWorldModel` (``"pose_warp"``).

    ``cfg``: the run config whose ``stage.pose_anchors`` (default ``"ctr"``),
    ``stage.pose_kinematics`` (default false), ``stage.pose_motion_frames`` (default 0),
    ``stage.pose_agents`` (default 0), ``stage.pose_leader``, ``stage.pose_leader_stop``
    (default false) and
    ``stage.pose_heads`` (default 1) the pose head uses
    and whose ``stage.movers`` (default ``"static"``) the forecast applies (validated by
    :func:`stage_settings`).
    """
    if kind != "pose_warp":
        return WorldModel(config)
    if cfg is None:
        return PoseWarpWorldModel(config)
    st = stage_settings(cfg)
    return PoseWarpWorldModel(
        config,
        anchors=st.pose_anchors,
        movers=st.movers,
        kinematics=st.pose_kinematics,
        motion_frames=st.pose_motion_frames,
        agents=st.pose_agents,
        leader=st.pose_leader,
        leader_stop=st.pose_leader_stop,
        pose_heads=st.pose_heads,
        bev_pool=st.pose_bev_pool,
    )


def extra_train_roots(cfg: Any) -> list[tuple[Path, Path]]:
    """(data root, infos folder) of each ``stage.extra_train_roots`` entry.

    Their train splits (GT occupancy) are added to the training windows; validation stays the
    run's own ``dataset.val_split``. Infos are read from
    ``<root>/renderworld_infos/<dataset.version>``, or from the one version folder a root holds
    (a scenario library is its own version, e.g. ``v1.0-scenarios``).

    Raises:
        ValueError: an entry that is not a folder with converted infos, one holding several
            versions none of which is ``dataset.version``, or a Camera-setting run
            (``stage.occ_root``), whose pseudo labels exist for its own data root only.
    """
    roots = cfg.stage.get("extra_train_roots") or []
    if roots and cfg.stage.get("occ_root"):
        raise ValueError(
            "stage.extra_train_roots: GT-occupancy roots cannot be mixed into a Camera-setting "
            "run (stage.occ_root is set)"
        )
    return [(Path(str(r)), _infos_of_root(Path(str(r)), str(cfg.dataset.version))) for r in roots]


def _infos_of_root(root: Path, version: str) -> Path:
    base = root / "renderworld_infos"
    if (base / version).is_dir():
        return base / version
    found = sorted(d for d in base.iterdir() if d.is_dir()) if base.is_dir() else []
    if len(found) == 1:
        return found[0]
    if not found:
        raise ValueError(
            f"stage.extra_train_roots: {base / version} does not exist; run tools/create_data.py "
            f"data_root={root} version=<its version> first"
        )
    raise ValueError(
        f"stage.extra_train_roots: {root} holds infos of several versions "
        f"{[d.name for d in found]} and none is dataset.version={version!r}"
    )


def frame_cache_dir(cfg: Any) -> Path | None:
    """Folder of the on-disk frame cache of ``stage.frame_cache``.

    ``true``: ``frames/`` under the package's cache root (``$RENDERWORLD_CACHE_DIR`` or
    ``~/.cache/renderworld``; entries are keyed by the file's path, so datasets never collide and
    a read-only dataset folder is never written); a string: that folder; ``false`` / null: no
    cache.
    """
    value = cfg.stage.get("frame_cache")
    if value is None or value is False:
        return None
    if value is True:
        return default_cache_root() / "frames"
    if isinstance(value, str) and value:
        return Path(value)
    raise ValueError(f"stage.frame_cache: expected true, false, null or a folder, got {value!r}")
