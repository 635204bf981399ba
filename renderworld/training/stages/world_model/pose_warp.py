"""The ``world_model`` stage with ``stage.forecaster: pose_warp`` (:class:`PoseWarpWorldModel`).

Training (teacher forcing): the pose head is fitted to the ground-truth future poses
(:func:`renderworld.world.pose.pose_loss`); the token network reads the history brought into
the current ego frame and the current frame warped along the **ground-truth** future poses (its
movers moved first by the model's rule: ``object_cv``, or its mover head, fitted before), and is
fitted to the future
frames' codes (cross-entropy). Loss = token CE + ``lambda_pose`` x pose loss.

Forecast (test time): poses from the pose head (history poses, the batch's command, current
frame), then :func:`renderworld.world.forecast.pose_warp_forecast` - the one forecaster the
planner calls too - with this stage's tokenizer and token cache. Only ``history_poses``, the
history occupancy and ``command`` of a batch are read; the windows' command is derived from the
GT future (as VAD / UniAD), and the row "model, command from history" passes the command the
same rule derives from the history instead, so that no input reads the future.

The functions take the stage itself; :class:`PoseWarpStage` names what they read of it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch
import torch.nn.functional as F

from renderworld.constants import COMMANDS
from renderworld.tokenizer import Tokens
from renderworld.training.stages.world_model.report import CHECKED, CHECKED_HISTORY_COMMAND
from renderworld.training.stages.world_model.windows import frame_keys
from renderworld.world.forecast import movers_of, pose_warp_forecast, warp_current
from renderworld.world.pose import align_history, pose_loss
from renderworld.world.pose_inputs import jittered_history, steady_history

if TYPE_CHECKING:
    from renderworld.constants import GridSpec
    from renderworld.tokenizer import SceneTokenizer
    from renderworld.training.stages.world_model.settings import EvalSetting, StageSettings

__all__ = [
    "PoseWarpStage",
    "POSE_METHODS",
    "POSE_PLANNERS",
    "checked_plans",
    "encode_frames",
    "mirror_command",
    "mirror_poses",
    "pose_forecast",
    "pose_teacher_forced",
    "pose_terms",
]

#: Forecast rows of the pose-warp model beside ``model`` (variants the note compares).
POSE_METHODS = ("model_warp", "model_net")
#: Planning rows only the pose-warp model has: its plan checked against its forecast.
POSE_PLANNERS = (CHECKED, CHECKED_HISTORY_COMMAND)
_CHUNK = 16


class PoseWarpStage(Protocol):
    """What the functions of this module read of the stage (a ``WorldModelStage``)."""

    cfg: Any  # the run config; ``stage.occ_root`` names the default token source
    settings: StageSettings  # history, tokenizer_ckpt, cache_tokens and the pose_* options
    grid: GridSpec  # the run's occupancy grid (warps, history alignment)
    _codes: dict[tuple[str, ...], torch.Tensor]  # the stage's token cache (filled here)

    def tokenizer_of(self, path: str | None) -> SceneTokenizer:
        """The frozen tokenizer of checkpoint ``path`` (None: ``stage.tokenizer_ckpt``)."""
        ...

    def _tokenizer_on(self, device: torch.device, path: str | None = None) -> SceneTokenizer:
        """The same tokenizer, moved to ``device``."""
        ...

    def window_tokens(
        self,
        batch: dict,
        frames: int,
        device: torch.device,
        inputs: str = "occ",
        source: str | None = None,
        tokenizer: str | None = None,
    ) -> torch.Tensor:
        """Codes [B, frames, G, h, w] of a batch's first ``frames`` frames (token cache)."""
        ...


@torch.no_grad()
def encode_frames(
    stage: PoseWarpStage,
    frames: torch.Tensor,
    keys: list[tuple] | None,
    device: torch.device,
    tokenizer: str | None = None,
) -> torch.Tensor:
    """Codes [N, G, h, w] int64 of occupancy frames [N, X, Y, Z] with the frozen tokenizer.

    ``keys`` (one hashable per frame, or None) cache the codes in the stage's token cache when
    ``stage.cache_tokens`` is on: only frames whose inputs are fixed (ground truth) may be keyed.
    """
    tok = stage._tokenizer_on(device, tokenizer)
    cache = stage._codes if (keys is not None and stage.settings.cache_tokens) else {}
    keys = keys if keys is not None else [None] * len(frames)
    todo = [i for i, k in enumerate(keys) if k is None or k not in cache]
    fresh: dict[int, torch.Tensor] = {}
    store = torch.int16 if max(tok.cfg.codebook_sizes) <= 2**15 else torch.int32
    for c in range(0, len(todo), _CHUNK):
        idx = todo[c : c + _CHUNK]
        with torch.autocast(device_type=device.type, enabled=False):
            codes = tok.encode(frames[idx].to(device)).indices.to("cpu", store)
        for i, code in zip(idx, codes):
            fresh[i] = code
            if keys[i] is not None:
                cache[keys[i]] = code
    out = [fresh[i] if i in fresh else cache[k] for i, k in enumerate(keys)]
    return torch.stack(out).to(device).long()


def pose_step_weights(kind: str, steps: int) -> torch.Tensor | None:
    """Per-step weights of the pose loss: ``uniform`` (None) or ``inverse`` (1/k, mean 1).

    ``inverse`` makes the near steps count more: a heading error costs as much forecast mIoU at
    1 s as at 3 s, while the far steps' errors (and so their gradients) are larger.
    """
    if kind == "uniform":
        return None
    if kind == "inverse":
        w = 1.0 / torch.arange(1, steps + 1, dtype=torch.float32)
        return w / w.mean()
    raise ValueError(f"stage.pose_step_weighting: expected 'uniform' or 'inverse', got {kind!r}")


def mirror_poses(poses: torch.Tensor) -> torch.Tensor:
    """Poses [..., 3] of the scene mirrored about the ego's x axis: (x, -y, -yaw)."""
    return poses * poses.new_tensor([1.0, -1.0, -1.0])


def mirror_command(command: torch.Tensor) -> torch.Tensor:
    """Command indices [B] with left and right swapped."""
    left, right = COMMANDS.index("left"), COMMANDS.index("right")
    out = command.clone()
    out[command == left], out[command == right] = right, left
    return out


def _history_codes(
    stage: PoseWarpStage,
    batch: dict,
    aligned: torch.Tensor,
    source: str,
    tokenizer: str | None,
) -> torch.Tensor:
    """Codes [B, H-1, G, h, w] of history frames t-H+1..t-1 already in the current ego frame
    (``aligned`` [B, H-1, X, Y, Z]; cached by frame and current frame)."""
    h = stage.settings.history
    b = aligned.shape[0]
    toks = frame_keys(batch, b, batch["occ"].shape[1])
    tok_key = stage.settings.tokenizer_ckpt if tokenizer is None else str(tokenizer)
    keys = [(tok_key, source, "aligned", toks[i][j], toks[i][h - 1]) for i in range(b)
            for j in range(h - 1)]  # fmt: skip
    device = batch["history_poses"].device
    return encode_frames(stage, aligned.flatten(0, 1), keys, device, tokenizer).view(
        b, h - 1, *_code_shape(stage, tokenizer)
    )


def _aligned_history_codes(
    stage: PoseWarpStage,
    batch: dict,
    occ_key: str,
    source: str,
    tokenizer: str | None,
    device: torch.device,
) -> torch.Tensor:
    """Codes [B, H-1, G, h, w] of history frames t-H+1..t-1 in the current ego frame."""
    h = stage.settings.history
    occ, poses = batch[occ_key][:, : h - 1], batch["history_poses"][:, : h - 1]
    aligned = align_history(occ, poses, stage.grid)
    return _history_codes(stage, batch, aligned, source, tokenizer).to(device)


def _code_shape(stage: PoseWarpStage, tokenizer: str | None) -> tuple[int, int, int]:
    cfg = stage.tokenizer_of(tokenizer).cfg
    return (len(cfg.codebook_sizes), *cfg.latent_shape)


def pose_terms(stage: PoseWarpStage, model: Any, batch: dict, inputs: str = "occ") -> dict:
    """The pose head's loss on a batch (:func:`renderworld.world.pose.pose_loss`: ``pose``,
    ``pose_l2`` in metres, ``pose_yaw`` in radians), with the stage's yaw weight and step
    weighting; in training with ``pose_mirror`` the mean over the scene and its mirror. With
    several pose heads each is scored on its own prediction: ``pose`` is their sum, ``pose_l2``
    and ``pose_yaw`` their mean."""
    st = stage.settings
    occ, cmd = batch[inputs], batch["command"].long()
    hist_poses, fut_poses = batch["history_poses"].float(), batch["future_poses"].float()
    valid = batch["future_mask"].bool()
    current = occ[:, st.history - 1]
    yaw_w = st.pose_yaw_weight
    steps = pose_step_weights(st.pose_step_weighting, st.future)
    history = occ[:, : st.history]
    if model.training and st.pose_history_dropout > 0:
        # Past-motion dropout (ChauffeurNet): some windows show the head a history at the last
        # step's speed and turn rate, so a trend alone (its own slowing, in closed loop) does
        # not carry into the plan unless the scene gives a reason.
        drop = torch.rand(hist_poses.shape[0], device=hist_poses.device) < st.pose_history_dropout
        steady = steady_history(hist_poses)
        hist_poses = torch.where(drop[:, None, None], steady, hist_poses)
    if model.training and st.pose_history_noise_m > 0:
        hist_poses = jittered_history(hist_poses, st.pose_history_noise_m)

    def loss(preds: torch.Tensor, gt: torch.Tensor) -> dict:
        # Each pose head on its own loss: ``pose`` summed over heads (each gets the gradient
        # it would get alone), the logged errors their mean.
        terms = [pose_loss(p, gt, valid, yaw_weight=yaw_w, step_weights=steps) for p in preds]
        out = {k: torch.stack([t[k] for t in terms]).mean() for k in terms[0]}
        out["pose"] = torch.stack([t["pose"] for t in terms]).sum()
        return out

    pred, _ = model.predict_poses(hist_poses, cmd, current, history, stage.grid, members=True)
    pl = loss(pred, fut_poses)
    if model.training and st.pose_mirror:
        # The mirrored scene (y -> -y, left <-> right) is as plausible: twice the pose data.
        m_pred, _ = model.predict_poses(mirror_poses(hist_poses), mirror_command(cmd),
                                        current.flip(2), history.flip(3), stage.grid,
                                        members=True)  # fmt: skip
        m = loss(m_pred, mirror_poses(fut_poses))
        pl = {k: 0.5 * (pl[k] + m[k]) for k in pl}
    return pl


def pose_teacher_forced(
    stage: PoseWarpStage,
    model: Any,
    batch: dict,
    inputs: str = "occ",
    source: str | None = None,
    tokenizer: str | None = None,
) -> dict[str, torch.Tensor]:
    """Loss terms of one batch: ``loss``, ``token_ce``, ``l2`` (pose position error, m),
    ``pose_yaw`` (rad).

    Args:
        inputs / source / tokenizer: the occupancy batch key, its source name (token-cache key)
            and the tokenizer checkpoint (None: the run's own, as in training).
    """
    st = stage.settings
    h, f = st.history, st.future
    device = batch["history_poses"].device
    if source is None:
        source = str(stage.cfg.stage.get("occ_root") or "gt")
    occ, cmd = batch[inputs], batch["command"].long()
    hist_poses, fut_poses = batch["history_poses"].float(), batch["future_poses"].float()
    valid = batch["future_mask"].bool()
    with torch.set_grad_enabled(torch.is_grad_enabled() and st.joint_pose_lr_scale != 0):
        pl = pose_terms(stage, model, batch, inputs)  # pose_joint_lr_scale=0: the head is frozen

    b = occ.shape[0]
    toks = frame_keys(batch, b, occ.shape[1])
    movers = getattr(model, "movers", "static")
    bases = warp_current(occ[:, :h], batch["history_poses"], fut_poses, stage.grid,
                         movers_of(model))  # fmt: skip
    bases = bases.flatten(0, 1)
    tok_key = st.tokenizer_ckpt if tokenizer is None else str(tokenizer)
    warp_key = "warp_gt" if movers == "static" else f"warp_gt_{movers}"
    keys = [(tok_key, source, warp_key, toks[i][h - 1], toks[i][h + k]) for i in range(b)
            for k in range(f)]  # fmt: skip
    shape = _code_shape(stage, tokenizer)
    base_codes = encode_frames(stage, bases, keys, device, tokenizer).view(b, f, *shape)
    hist_codes = _aligned_history_codes(stage, batch, inputs, source, tokenizer, device)
    target = stage.window_tokens(batch, h + f, device, inputs, source, tokenizer)[:, h:]
    seq = torch.cat([hist_codes, base_codes], dim=1)
    seq_poses = torch.cat([hist_poses[:, : h - 1], fut_poses], dim=1)
    logits = model(seq, seq_poses, cmd)
    w = valid.float()
    ces = []
    for g, lg in enumerate(logits):
        rows = lg.permute(0, 1, 3, 4, 2)  # [B, S, h, w, K]: codes last, as the model wrote them
        ce = F.cross_entropy(rows.reshape(-1, rows.shape[-1]), target[:, :, g].reshape(-1),
                             reduction="none").view(b, f, -1)  # fmt: skip
        ces.append((ce.mean(dim=-1) * w).sum() / w.sum().clamp_min(1.0))
    token_ce = torch.stack(ces).mean()
    return {
        "loss": token_ce + st.lambda_pose * pl["pose"],
        "token_ce": token_ce,
        "l2": pl["pose_l2"],
        "pose_yaw": pl["pose_yaw"],
    }


class _StageCodec:
    """The stage's :class:`~renderworld.world.forecast.FrameCodec`: its frozen tokenizer, the
    aligned history's codes cached by frame (ground truth only), warped frames never cached."""

    def __init__(
        self, stage: PoseWarpStage, batch: dict, setting: EvalSetting, device: torch.device
    ):
        self.stage, self.batch, self.setting, self.device = stage, batch, setting, device

    def encode(self, aligned: torch.Tensor, warped: torch.Tensor) -> tuple[torch.Tensor, ...]:
        st, b, f = self.setting, warped.shape[0], warped.shape[1]
        base = encode_frames(self.stage, warped.flatten(0, 1), None, self.device, st.tokenizer)
        base = base.view(b, f, *_code_shape(self.stage, st.tokenizer))
        return _history_codes(self.stage, self.batch, aligned, st.source, st.tokenizer), base

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        tok = self.stage._tokenizer_on(self.device, self.setting.tokenizer)
        names, sizes = tok.cfg.codebook_names, tok.cfg.codebook_sizes
        with torch.autocast(device_type=self.device.type, enabled=False):
            return torch.stack(
                [tok.decode(Tokens(codes[:, k], sizes, names)) for k in range(codes.shape[1])],
                dim=1,
            )


@torch.no_grad()
def pose_forecast(
    stage: PoseWarpStage, model: Any, batch: dict, setting: EvalSetting
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Forecasts ``model`` / ``model_warp`` / ``model_net`` [B, S, X, Y, Z] and the planned
    poses [B, S, 3] (x, y, yaw; metres, radians, current ego frame) of one setting's inputs
    (:func:`renderworld.world.forecast.pose_warp_forecast`, as the planner forecasts).

    Reads only the history occupancy (``setting.inputs``), ``history_poses`` and ``command``.
    """
    h = stage.settings.history
    history = batch[setting.inputs][:, :h]
    cmd = batch["command"].long()
    device = batch["history_poses"].device
    poses, _ = model.predict_poses(
        batch["history_poses"].float(), cmd, history[:, h - 1], history, stage.grid
    )
    codec = _StageCodec(stage, batch, setting, device)
    fc = pose_warp_forecast(model, history, batch["history_poses"], poses, cmd, stage.grid, codec)
    return {"model": fc.forecast, "model_warp": fc.warp, "model_net": fc.net}, poses


def checked_plans(
    stage: PoseWarpStage, model: Any, batch: dict, setting: EvalSetting, poses: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's plans checked against its own forecast, as a planner bundle drives them
    (:func:`renderworld.planning.checked.check_plan`; the planner's default knobs, or those the
    evaluation's ``check`` sets, e.g. ``tools/eval.py ... check={plan_margin: 0.3}``).

    Args:
        stage: the stage (its history length and grid).
        model: the pose-warp model (its mover forecast).
        batch: a collated batch (the setting's history occupancy and ``history_poses`` read).
        setting: whose history occupancy the forecast is made of.
        poses: [B, S, 3] the model's predicted poses.

    Returns:
        (trajectories [B, S, 2] metres, headings [B, S] radians), current ego frame, on the
        device and in the dtype of ``poses``.
    """
    from renderworld.planning.candidates import check_config
    from renderworld.planning.checked import check_plan
    from renderworld.planning.scene import model_forecaster

    h = stage.settings.history
    occ = batch[setting.inputs][:, :h].cpu().numpy()
    hist = batch["history_poses"].double().cpu().numpy()
    plan = poses.double().cpu().numpy()
    movers = model_forecaster(model)
    knobs = stage.cfg.get("check")  # tools/eval.py check={...}; absent in training
    config = check_config(knobs) if knobs else None
    out = [check_plan(o, hp, p, stage.grid, config, movers=movers)
           for o, hp, p in zip(occ, hist, plan)]  # fmt: skip
    traj = torch.from_numpy(np.stack([c.trajectory for c in out])).to(poses)
    yaws = torch.from_numpy(np.stack([c.yaws for c in out])).to(poses)
    return traj, yaws
