"""Pictures of a ``world_model`` evaluation (written by ``tools/eval.py`` into its run dir).

* ``bev_forecast.png``: one turning validation window (:func:`turning_window`) in bird's-eye
  view at t = 0 and +1/+2/+3 s; rows GT occupancy, the Img2Occ pseudo labels (when the Camera
  setting is evaluated), each setting's model forecast (at t = 0: its tokenized input, what the
  model sees of the current frame) and, from the first setting's input, Copy&Paste, CV-warp and
  the GT-pose warp reference.
* ``trajectories.png``: a few validation windows spread over the split; GT future, the model's
  plan (first setting) and the constant-velocity baseline over the current GT frame, ego box.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import default_collate

from renderworld.constants import COMMANDS, KEYFRAME_DT
from renderworld.tokenizer import Tokens
from renderworld.training.figures import bev_forecast_figure, trajectory_figure

__all__ = ["BEV_PNG", "TRAJ_PNG", "write_pictures", "picture_windows", "turning_window"]

BEV_PNG = "bev_forecast.png"
TRAJ_PNG = "trajectories.png"


def picture_windows(n_windows: int, count: int) -> list[int]:
    """``count`` window indices spread evenly over ``n_windows`` (fewer when there are fewer).

    Raises:
        ValueError: negative ``n_windows`` or ``count`` < 1.
    """
    if n_windows < 0 or count < 1:
        raise ValueError(f"n_windows/count: expected >= 0 and >= 1, got {n_windows}, {count}")
    if n_windows == 0:
        return []
    return sorted({int(i) for i in np.linspace(0, n_windows - 1, min(count, n_windows))})


def turning_window(val_set) -> int:
    """Index of the turning window nearest the middle of the split (the middle when none turns).

    Turning: the ground-truth heading changes by more than ``TURN_THRESHOLD_DEG`` within the
    window's future (see :func:`~renderworld.training.stages.world_model.splits.turning_windows`).
    """
    from renderworld.training.stages.world_model.splits import turning_windows

    n = len(val_set)
    for i in sorted(range(n), key=lambda j: abs(j - n // 2)):
        item = val_set[i]
        if bool(turning_windows(item["future_poses"][None], item["future_mask"][None])[0]):
            return i
    return n // 2


def _batch(stage, val_set, idx: list[int], device) -> dict:
    return stage.transfer_batch(default_collate([val_set[i] for i in idx]), device)


@torch.no_grad()
def write_pictures(stage: Any, model: torch.nn.Module, val_set, run_dir: Path) -> list[Path]:
    """Write ``bev_forecast.png`` and ``trajectories.png`` into ``run_dir``; return their paths.

    Args:
        stage: the :class:`WorldModelStage` (settings, tokenizer, ``forecast``).
        model: the evaluated world model (the first setting's).
        val_set: the stage's validation windows.
        run_dir: the eval run directory.
    """
    raw = model.module if hasattr(model, "module") else model
    device = next(raw.parameters()).device
    h, f, grid = stage.settings.history, stage.settings.future, stage.grid
    steps = [round(t / KEYFRAME_DT) for t in stage.horizons]
    cols = ["t = 0 (now)", *(f"+{t:g} s" for t in stage.horizons)]
    settings = stage.eval_settings
    out = []

    mid = [turning_window(val_set)]
    batch = _batch(stage, val_set, mid, device)
    gt = batch.get("occ_target", batch["occ"])[0].cpu().numpy()  # [T, X, Y, Z]
    rows = [("GT", [gt[h - 1 + k] for k in (0, *steps)])]
    if "occ_target" in batch:  # the dataset's own source is the pseudo labels
        pseudo = batch["occ"][0].cpu().numpy()
        rows.append(("Img2Occ pseudo label", [pseudo[h - 1 + k] for k in (0, *steps)]))
    for i, s in enumerate(settings):
        tok = stage._tokenizer_on(device, s.tokenizer)
        forecasts, _ = stage.forecast(stage.setting_model(raw, s), batch, s, None)
        cur = batch[s.inputs][:, h - 1]
        idx = tok.encode(cur).indices
        seen = tok.decode(Tokens(idx, tok.cfg.codebook_sizes, tok.cfg.codebook_names))[0]
        fc = forecasts["model"][0].cpu().numpy()
        frames = [seen.cpu().numpy().astype(np.uint8), *(fc[k - 1] for k in steps)]
        rows.append((f"{s.label} forecast", [np.asarray(x, dtype=np.uint8) for x in frames]))
        if i == 0:  # the baselines and the reference beside the model, from the same input
            forecasts.update(stage.references(batch, s))
            now = cur[0].cpu().numpy().astype(np.uint8)
            for key, label in (("copy_paste", "Copy&Paste"), ("warp_cv", "CV-warp"),
                               ("warp_gt_pose", "GT-pose warp (ref.)")):  # fmt: skip
                other = forecasts[key][0].cpu().numpy()
                rows.append((label, [now, *(np.asarray(other[k - 1], np.uint8) for k in steps)]))
    token = batch["meta"]["sample_tokens"][h - 1][0]
    cmd = COMMANDS[int(batch["command"][0])]
    out.append(
        bev_forecast_figure(
            rows, cols, grid, run_dir / BEV_PNG,
            title=f"val window {mid[0]} (current sample {str(token)[:8]}, command {cmd}); "
            "model rows at t = 0: the tokenized input; GT-pose warp reads the future",
        )
    )  # fmt: skip

    first = settings[0]
    idx = picture_windows(len(val_set), 4)
    batch = _batch(stage, val_set, idx, device)
    _, trajs = stage.forecast(stage.setting_model(raw, first), batch, first, None)
    gt_occ = batch.get("occ_target", batch["occ"])[:, h - 1].cpu().numpy()
    panels = []
    for b, i in enumerate(idx):
        n_ok = int(batch["future_mask"][b].sum())
        panels.append(
            {
                "occ": gt_occ[b],
                "trajectories": {
                    "GT future": batch["future_traj"][b, :n_ok].cpu().numpy(),
                    "model": trajs["model"][b].cpu().numpy(),
                    "CV baseline": trajs["cv_traj"][b].cpu().numpy(),
                },
                "title": f"window {i}, {COMMANDS[int(batch['command'][b])]}",
            }
        )
    # Zoom on the plans: from behind the ego box to past the farthest waypoint, square.
    reach = max(
        float(np.abs(t).max(initial=0.0)) for p in panels for t in p["trajectories"].values()
    )
    span = max(16.0, reach + 10.0)
    view = (-6.0, span - 6.0, -span / 2, span / 2)
    out.append(
        trajectory_figure(
            panels, grid, run_dir / TRAJ_PNG, view=view,
            title=f"{first.label} setting: plans over {f * KEYFRAME_DT:g} s vs GT (current GT "
            "frame underneath)",
        )
    )  # fmt: skip
    return out
