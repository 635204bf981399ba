"""Pictures of a ``world_model`` evaluation (written by ``tools/eval.py`` into its run dir).

* ``bev_forecast.png``: one turning validation window (:func:`turning_window`) in bird's-eye
  view at t = 0 and +1/+2/+3 s; rows GT occupancy, the Img2Occ pseudo labels (when the Camera
  setting is evaluated), each setting's model forecast (at t = 0: its tokenized input, what the
  model sees of the current frame) and, from the first setting's input, Copy&Paste, CV-warp and
  the GT-pose warp reference.
* ``bev_movers.png``: one validation window where a car moves (:func:`mover_window`), at the
  same times; rows GT occupancy, the first setting's model forecast, the object-CV warp and
  the GT-pose warp reference (the last two from that setting's input).
* ``trajectories.png``: a few validation windows spread over the split; GT future, the model's
  plan (first setting) and the constant-velocity baseline over the current GT frame, ego box.
* ``movers_<behaviour>.png`` for ``cut_in`` and ``lead_brake`` when the split holds such
  scenes (:func:`behaviour_windows`: the first such scene, its second window): GT, the model,
  the object-CV warp, and both under the ground-truth poses (the movers alone).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch.utils.data import default_collate

from renderworld.constants import (
    COMMANDS,
    KEYFRAME_DT,
    MOVABLE_CLASS_IDS,
    OCC3D_CLASSES,
    GridSpec,
)
from renderworld.tokenizer import Tokens
from renderworld.training.figures import bev_forecast_figure, trajectory_figure
from renderworld.world.baselines import constant_turn_rate_poses
from renderworld.world.movers import bev_components, object_velocities

__all__ = [
    "BEHAVIOUR_PICTURES",
    "BEV_PNG",
    "MOVERS_PNG",
    "TRAJ_PNG",
    "MoverWindow",
    "behaviour_windows",
    "mover_window",
    "picture_windows",
    "turning_window",
    "write_pictures",
]

BEV_PNG = "bev_forecast.png"
#: Behaviours drawn in a picture of their own (``movers_<behaviour>.png``).
BEHAVIOUR_PICTURES = ("cut_in", "lead_brake")
MOVERS_PNG = "bev_movers.png"
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


class MoverWindow(NamedTuple):
    """The window :func:`mover_window` picked.

    Attributes:
        index: the window's index in the validation set.
        speed_mps: its fastest mover's speed, metres per second (0.0: none moves).
        class_id: that mover's Occ3D class id (None: none moves, the turning window instead).
        centroid_m: its bird's-eye-view centroid (x, y), metres in the window's current ego
            frame (None: none moves).
    """

    index: int
    speed_mps: float
    class_id: int | None
    centroid_m: tuple[float, float] | None = None


def _on_border(cells: np.ndarray) -> bool:
    """Whether BEV cells [X, Y] bool touch the edge of the grid."""
    return bool(cells[0].any() or cells[-1].any() or cells[:, 0].any() or cells[:, -1].any())


def _in_view(c: np.ndarray, v: np.ndarray, horizon_pose: np.ndarray, horizon_s: float,
             grid: GridSpec) -> bool:  # fmt: skip
    """Whether a mover at ``c`` [2] moving at ``v`` [2] (current ego frame) still lies on the
    grid after ``horizon_s`` seconds, seen from the ego at ``horizon_pose`` (x, y, yaw)."""
    x, y, yaw = (float(t) for t in horizon_pose)
    d = c + v * horizon_s - (x, y)
    p = (np.cos(yaw) * d[0] + np.sin(yaw) * d[1], -np.sin(yaw) * d[0] + np.cos(yaw) * d[1])
    lo, hi = grid.range_min, grid.range_max
    return bool(lo[0] <= p[0] < hi[0] and lo[1] <= p[1] < hi[1])


def mover_window(
    val_set,
    grid: GridSpec,
    history: int,
    future: int,
    lag: int = 2,
    classes: tuple[str, ...] = ("car",),
) -> MoverWindow:
    """The window whose current ground-truth frame holds the fastest mover that stays in view.

    Each window's movable bird's-eye-view components of ``classes`` of its current frame t
    (:func:`~renderworld.world.movers.bev_components`) are matched to those of its frame
    t - ``lag`` brought into the current ego frame with the window's ``history_poses``
    (:func:`~renderworld.world.movers.object_velocities`, the object-CV warp's rule; parked
    objects have zero speed). Skipped: a component touching the grid's border (part of it lies
    outside the grid, so its centroid shifts as it enters or leaves), and one whose
    constant-velocity position at the last future frame, seen from the ego's constant-turn-rate
    pose then (:func:`~renderworld.world.baselines.constant_turn_rate_poses`), is off the grid
    (it would leave the picture). Only history frames are read, of the ground truth
    (``occ_target`` where the window has it, else ``occ``). The largest speed wins, ties to the
    lower index; when no mover is left, :func:`turning_window` with speed 0.

    Args:
        val_set: windows (items with ``occ`` [T, X, Y, Z] uint8, ``history_poses`` [H, 3]).
        grid: the occupancy grid of the windows.
        history: H, history frames per window (the current frame is H - 1).
        future: S, future frames per window (the last one is the picture's last column).
        lag: frames between the two compared frames (1 <= lag < H).
        classes: Occ3D names of the movable classes considered (all are matched).

    Raises:
        ValueError: ``lag`` outside [1, ``history`` - 1], ``future`` < 1, or a name of
            ``classes`` that is not a movable Occ3D class.
    """
    if not 1 <= lag < history:
        raise ValueError(f"lag: expected an int in [1, {history - 1}], got {lag!r}")
    if future < 1:
        raise ValueError(f"future: expected >= 1, got {future!r}")
    movable = {OCC3D_CLASSES[c]: c for c in MOVABLE_CLASS_IDS}
    if not classes or any(c not in movable for c in classes):
        raise ValueError(f"classes: expected names among {sorted(movable)}, got {classes!r}")
    wanted = {movable[c] for c in classes}
    best = MoverWindow(-1, 0.0, None, None)
    for i in range(len(val_set)):
        item = val_set[i]
        occ = np.asarray(item.get("occ_target", item["occ"]))
        now = bev_components(occ[history - 1], grid)
        if not now:
            continue
        poses = np.asarray(item["history_poses"], dtype=np.float64)[:history]
        past = bev_components(occ[history - 1 - lag], grid)
        vel = object_velocities(now, past, poses[history - 1 - lag], lag * KEYFRAME_DT, grid)
        last = constant_turn_rate_poses(poses, future)[-1]
        shown = [
            cls in wanted
            and not _on_border(cells)
            and _in_view(c, v, last, future * KEYFRAME_DT, grid)
            for (cls, cells, c), v in zip(now, vel)
        ]
        speed = np.where(shown, np.linalg.norm(vel, axis=1), 0.0)
        j = int(np.argmax(speed))
        if speed[j] > best.speed_mps:  # strictly faster: ties keep the lower index
            c = now[j][2]
            best = MoverWindow(i, float(speed[j]), int(now[j][0]), (float(c[0]), float(c[1])))
    if best.class_id is None:
        return MoverWindow(turning_window(val_set), 0.0, None)
    return best


def behaviour_windows(val_set, behaviours=BEHAVIOUR_PICTURES) -> dict[str, int]:
    """``{behaviour: window index}``: the second window of the first scene of each behaviour
    the split holds (its scenes' descriptions, :func:`renderworld.sim.scene.behaviour_of`),
    where the scripted interaction of the simulated scenes happens within its 3 s."""
    from renderworld.sim.scene import behaviour_of

    first: dict[str, tuple[str, list[int]]] = {}  # behaviour -> (its first scene, windows)
    for i in range(len(val_set)):
        meta = val_set[i]["meta"]
        b = behaviour_of(meta.get("scene_description", ""))
        if b not in behaviours:
            continue
        scene, windows = first.setdefault(b, (meta["scene"], []))
        if meta["scene"] == scene:
            windows.append(i)
    return {b: w[1] if len(w) > 1 else w[0] for b, (_, w) in first.items()}


def _batch(stage, val_set, idx: list[int], device) -> dict:
    return stage.transfer_batch(default_collate([val_set[i] for i in idx]), device)


def _model_row(stage: Any, raw, batch: dict, setting, steps: list[int]):
    """(frames, forecasts) of window 0 of ``batch``: the tokenized current input then the
    model's forecast at ``steps``; ``forecasts`` is :meth:`forecast`'s dict of the setting."""
    h = stage.settings.history
    tok = stage._tokenizer_on(batch["history_poses"].device, setting.tokenizer)
    forecasts, _ = stage.forecast(stage.setting_model(raw, setting), batch, setting, None)
    idx = tok.encode(batch[setting.inputs][:, h - 1]).indices
    seen = tok.decode(Tokens(idx, tok.cfg.codebook_sizes, tok.cfg.codebook_names))[0]
    fc = forecasts["model"][0].cpu().numpy()
    frames = [seen.cpu().numpy(), *(fc[k - 1] for k in steps)]
    return [np.asarray(x, dtype=np.uint8) for x in frames], forecasts


def _other_rows(stage, batch, setting, forecasts, steps, keys) -> list:
    """Rows (label, frames) of the forecasts ``keys`` {method: label} of window 0 of ``batch``
    (references included), each from the setting's current frame shown at t = 0."""
    forecasts = {**forecasts, **stage.references(batch, setting)}
    now = batch[setting.inputs][0, stage.settings.history - 1].cpu().numpy().astype(np.uint8)
    rows = []
    for key, label in keys.items():
        other = forecasts[key][0].cpu().numpy()
        rows.append((label, [now, *(np.asarray(other[k - 1], np.uint8) for k in steps)]))
    return rows


def _gt_row(batch: dict, h: int, steps: list[int]) -> tuple[str, list[np.ndarray]]:
    gt = batch.get("occ_target", batch["occ"])[0].cpu().numpy()  # [T, X, Y, Z]
    return ("GT", [gt[h - 1 + k] for k in (0, *steps)])


@torch.no_grad()
def write_pictures(stage: Any, model: torch.nn.Module, val_set, run_dir: Path) -> list[Path]:
    """Write ``bev_forecast.png``, ``bev_movers.png`` and ``trajectories.png`` into
    ``run_dir``; return their paths.

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
    rows = [_gt_row(batch, h, steps)]
    if "occ_target" in batch:  # the dataset's own source is the pseudo labels
        pseudo = batch["occ"][0].cpu().numpy()
        rows.append(("Img2Occ pseudo label", [pseudo[h - 1 + k] for k in (0, *steps)]))
    for i, s in enumerate(settings):
        frames, forecasts = _model_row(stage, raw, batch, s, steps)
        rows.append((f"{s.label} forecast", frames))
        if i == 0:  # the baselines and the reference beside the model, from the same input
            keys = {"copy_paste": "Copy&Paste", "warp_cv": "CV-warp",
                    "warp_gt_pose": "GT-pose warp (ref.)"}  # fmt: skip
            rows += _other_rows(stage, batch, s, forecasts, steps, keys)
    token = batch["meta"]["sample_tokens"][h - 1][0]
    cmd = COMMANDS[int(batch["command"][0])]
    out.append(
        bev_forecast_figure(
            rows, cols, grid, run_dir / BEV_PNG,
            title=f"val window {mid[0]} (current sample {str(token)[:8]}, command {cmd}); "
            "model rows at t = 0: the tokenized input; GT-pose warp reads the future",
        )
    )  # fmt: skip
    out.append(_movers_picture(stage, raw, val_set, run_dir, device, steps, cols))
    out += _behaviour_pictures(stage, raw, val_set, run_dir, device, steps, cols)

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


def _movers_picture(stage, raw, val_set, run_dir: Path, device, steps, cols) -> Path:
    """``bev_movers.png``: the :func:`mover_window` window; GT, the first setting's model,
    object-CV warp, GT-pose warp."""
    h, first = stage.settings.history, stage.eval_settings[0]
    f = stage.settings.future
    pick = mover_window(val_set, stage.grid, h, f, lag=min(2, h - 1)) if h > 1 else None
    if pick is None:
        pick = MoverWindow(turning_window(val_set), 0.0, None)
    batch = _batch(stage, val_set, [pick.index], device)
    frames, forecasts = _model_row(stage, raw, batch, first, steps)
    rows = [_gt_row(batch, h, steps), (f"{first.label} forecast", frames)]
    keys = {"warp_object_cv": "object-CV warp", "warp_gt_pose": "GT-pose warp (ref.)"}
    rows += _other_rows(stage, batch, first, forecasts, steps, keys)
    scene, token = batch["meta"]["scene"][0], batch["meta"]["sample_tokens"][h - 1][0]
    where = f"val window {pick.index} ({scene}, current sample {str(token)[:8]})"
    if pick.class_id is None:
        what = "no car in the split moves and stays in view: the turning window"
    else:
        name = OCC3D_CLASSES[pick.class_id]
        what = f"fastest {name} in view: {pick.speed_mps:.1f} m/s (circled at t = 0)"
    return bev_forecast_figure(
        rows, cols, stage.grid, run_dir / MOVERS_PNG,
        title=f"{where}; {what}\nmodel row at t = 0: the tokenized input; GT-pose warp reads "
        "the future",
        marks=[pick.centroid_m] if pick.centroid_m is not None else (),
    )  # fmt: skip


def _behaviour_pictures(stage, raw, val_set, run_dir: Path, device, steps, cols) -> list[Path]:
    """``movers_<behaviour>.png`` of :func:`behaviour_windows` (module docstring)."""
    from renderworld.training.stages.world_model.report import MODEL_MOVERS

    h, first = stage.settings.history, stage.eval_settings[0]
    out = []
    for behaviour, i in behaviour_windows(val_set).items():
        batch = _batch(stage, val_set, [i], device)
        frames, forecasts = _model_row(stage, raw, batch, first, steps)
        rows = [_gt_row(batch, h, steps), ("model", frames)]
        keys = {"warp_object_cv": "object-CV warp"}
        if MODEL_MOVERS in forecasts:
            keys[MODEL_MOVERS] = "GT poses + model movers (ref.)"
        keys["warp_gt_object_cv"] = "GT poses + object-CV movers (ref.)"
        rows += _other_rows(stage, batch, first, forecasts, steps, keys)
        scene = batch["meta"]["scene"][0]
        out.append(
            bev_forecast_figure(
                rows, cols, stage.grid, run_dir / f"movers_{behaviour}.png",
                title=f"{behaviour.replace('_', ' ')}: {scene}, val window {i}; model row at "
                "t = 0: the tokenized input; the (ref.) rows read the future poses",
            )
        )  # fmt: skip
    return out
