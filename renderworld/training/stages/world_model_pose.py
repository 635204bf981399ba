"""The ``world_model`` stage with ``stage.forecaster: pose_warp`` (:class:`PoseWarpWorldModel`).

Training (teacher forcing): the pose head is fitted to the ground-truth future poses
(:func:`renderworld.world.pose.pose_loss`); the token network reads the history brought into
the current ego frame and the current frame warped along the **ground-truth** future poses, and
is fitted to the future frames' codes (cross-entropy). Loss = token CE + ``lambda_pose`` x pose
loss.

Forecast (test time, leak-free): poses from the pose head (history poses, current command,
current frame); the current frame warped along them (``model, warp only``); the token network
on the aligned history and those warped frames, decoded (``model, tokens only``); the forecast
``model`` takes the warp wherever its source lies on the current grid and, where it does not
(newly revealed space), the decoded tokens of the classes the current frame holds (free
otherwise). Only ``history_poses``, the history occupancy and
``command`` of a batch are read.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from renderworld.constants import COMMANDS, FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer import Tokens
from renderworld.training.stages import world_model_eval as wme
from renderworld.world import warp_along_poses
from renderworld.world.pose import align_history, pose_loss

__all__ = [
    "POSE_METHODS",
    "encode_frames",
    "mirror_command",
    "mirror_poses",
    "pose_forecast",
    "pose_teacher_forced",
]

#: Forecast rows of the pose-warp model beside ``model`` (variants the note compares).
POSE_METHODS = ("model_warp", "model_net")
_CHUNK = 16


@torch.no_grad()
def encode_frames(
    stage: Any,
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


def _aligned_history_codes(stage, batch, occ_key, source, tokenizer, device) -> torch.Tensor:
    """Codes [B, H-1, G, h, w] of history frames t-H+1..t-1 in the current ego frame."""
    h = stage.settings.history
    occ, poses = batch[occ_key][:, : h - 1], batch["history_poses"][:, : h - 1]
    b = occ.shape[0]
    aligned = align_history(occ, poses, stage.grid).flatten(0, 1)
    toks = wme.frame_keys(batch, b, batch["occ"].shape[1])
    tok_key = stage.settings.tokenizer_ckpt if tokenizer is None else str(tokenizer)
    keys = [(tok_key, source, "aligned", toks[i][j], toks[i][h - 1]) for i in range(b)
            for j in range(h - 1)]  # fmt: skip
    return encode_frames(stage, aligned, keys, device, tokenizer).view(
        b, h - 1, *_code_shape(stage, tokenizer)
    )


def _code_shape(stage, tokenizer) -> tuple[int, int, int]:
    cfg = stage.tokenizer_of(tokenizer).cfg
    return (len(cfg.codebook_sizes), *cfg.latent_shape)


def pose_teacher_forced(
    stage: Any,
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
    current = occ[:, h - 1]
    yaw_w = st.pose_yaw_weight
    steps = pose_step_weights(st.pose_step_weighting, f)
    pred, _ = model.predict_poses(hist_poses, cmd, current)
    pl = pose_loss(pred, fut_poses, valid, yaw_weight=yaw_w, step_weights=steps)
    if model.training and st.pose_mirror:
        # The mirrored scene (y -> -y, left <-> right) is as plausible: twice the pose data.
        m_pred, _ = model.predict_poses(mirror_poses(hist_poses), mirror_command(cmd),
                                        current.flip(2))  # fmt: skip
        m = pose_loss(m_pred, mirror_poses(fut_poses), valid, yaw_weight=yaw_w, step_weights=steps)
        pl = {k: 0.5 * (pl[k] + m[k]) for k in pl}

    b = occ.shape[0]
    toks = wme.frame_keys(batch, b, occ.shape[1])
    bases = warp_along_poses(current, fut_poses, stage.grid).flatten(0, 1)
    tok_key = st.tokenizer_ckpt if tokenizer is None else str(tokenizer)
    keys = [(tok_key, source, "warp_gt", toks[i][h - 1], toks[i][h + k]) for i in range(b)
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
        ce = F.cross_entropy(lg.flatten(0, 1), target[:, :, g].flatten(0, 1), reduction="none")
        ces.append((ce.mean(dim=(-2, -1)).view(b, f) * w).sum() / w.sum().clamp_min(1.0))
    token_ce = torch.stack(ces).mean()
    return {
        "loss": token_ce + st.lambda_pose * pl["pose"],
        "token_ce": token_ce,
        "l2": pl["pose_l2"],
        "pose_yaw": pl["pose_yaw"],
    }


@torch.no_grad()
def pose_forecast(
    stage: Any, model: Any, batch: dict, setting: Any
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Forecasts ``model`` / ``model_warp`` / ``model_net`` [B, S, X, Y, Z] and the planned
    poses [B, S, 3] (x, y, yaw; metres, radians, current ego frame) of one setting's inputs.

    Reads only the history occupancy (``setting.inputs``), ``history_poses`` and ``command``.
    """
    st = stage.settings
    h, f = st.history, st.future
    occ = batch[setting.inputs]
    hist_poses = batch["history_poses"].float()
    cmd = batch["command"].long()
    device = hist_poses.device
    current = occ[:, h - 1]
    poses, _ = model.predict_poses(hist_poses, cmd, current)
    warped = warp_along_poses(current, poses.double(), stage.grid)  # [B, S, X, Y, Z]
    ones = torch.ones(current.shape[:3], dtype=torch.uint8, device=device)
    inside = warp_along_poses(ones[..., None], poses.double(), _bev_grid(stage), fill=0)[..., 0]
    b = occ.shape[0]
    base_codes = encode_frames(stage, warped.flatten(0, 1), None, device, setting.tokenizer)
    base_codes = base_codes.view(b, f, *_code_shape(stage, setting.tokenizer))
    hist_codes = _aligned_history_codes(
        stage, batch, setting.inputs, setting.source, setting.tokenizer, device
    )
    seq = torch.cat([hist_codes, base_codes], dim=1)
    seq_poses = torch.cat([hist_poses[:, : h - 1], poses], dim=1)
    logits = model(seq, seq_poses, cmd)
    codes = torch.stack([lg.argmax(dim=2) for lg in logits], dim=2)  # [B, S, G, h, w]
    tok = stage._tokenizer_on(device, setting.tokenizer)
    with torch.autocast(device_type=device.type, enabled=False):
        net = torch.stack(
            [tok.decode(Tokens(codes[:, k], tok.cfg.codebook_sizes, tok.cfg.codebook_names))
             for k in range(f)], dim=1,
        ).to(warped.dtype)  # fmt: skip
    # Newly revealed space continues what the current frame shows: decoded classes the current
    # frame does not hold there are left free (a token decoder's stray classes would each add
    # a present class at IoU ~0 to the mIoU).
    seen = torch.zeros(b, NUM_OCC3D_CLASSES, dtype=torch.bool, device=device)
    seen.scatter_(1, current.flatten(1).long(), True)
    fill = torch.where(seen.gather(1, net.flatten(1).long()).view(net.shape), net,
                       torch.full_like(net, FREE_ID))  # fmt: skip
    model_fc = torch.where(inside[..., None].bool(), warped, fill)
    return {"model": model_fc, "model_warp": warped, "model_net": net}, poses


def _bev_grid(stage):
    """The stage grid with one z level (the inside-the-grid mask is the same at every z)."""
    from renderworld.constants import GridSpec

    g = stage.grid
    lo, hi = list(g.range_min), list(g.range_max)
    return GridSpec(f"{g.name}-bev", tuple(lo), tuple(hi), (g.shape[0], g.shape[1], 1))
