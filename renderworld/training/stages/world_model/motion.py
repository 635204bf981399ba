"""Motion metrics of the forecast's movers: ADE / FDE of moving road users' centres.

What motion forecasting (Argoverse, Waymo Open Motion) reports, for the movers a pose-warp
forecast moves. Per window, the current frame's movers are tracked through the history
(:func:`renderworld.world.tracks.track_movers`) and matched to their annotated boxes
(:func:`~renderworld.training.stages.world_model.mover_fit.mover_targets`: the nearest box of
their class, then that road user's boxes in the future frames by instance index). A mover is
**moving** when its box moves at least :data:`MOVING_M` by the last future step. Each method
predicts its displacement at every future step:

* ``model``: the model's own movers (its mover head with ``movers="learned"``; the object-CV
  rule with ``"object_cv"``; nothing moves with ``"static"``);
* ``object_cv``: the object-CV rule of the object-CV warp baseline (its velocity against frame
  t-2, :func:`renderworld.world.movers.object_velocities`).

Errors are Euclidean distances (metres) between the predicted and the true displacement, i.e.
between the centres if the mover's centroid were its box centre. ``FDE@h`` is the mean error at
h's step over the moving movers annotated there; ``ADE@h`` the mean over every step up to h.
Counts are kept per group: all movers, per class and per scene behaviour (from the scene's
description, :func:`renderworld.sim.scene.behaviour_of`; empty for real data).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from renderworld.constants import KEYFRAME_DT, MOVABLE_CLASS_IDS, OCC3D_CLASSES, GridSpec
from renderworld.sim.scene import BEHAVIOURS, behaviour_of
from renderworld.training.stages.world_model.mover_fit import mover_targets
from renderworld.world.learned_movers import head_displacements
from renderworld.world.movers import bev_components, object_velocities
from renderworld.world.tracks import MoverTrack, track_movers

__all__ = [
    "MOTION_METHODS",
    "MOVING_M",
    "add_motion_stats",
    "empty_motion_stats",
    "motion_from_stats",
    "motion_groups",
    "motion_table",
    "write_motion",
]

MOTION_METHODS = ("model", "object_cv")
#: A road user moving at least this far (metres) by the last future step is "moving".
MOVING_M = 1.0
_LAG = 2


def motion_groups() -> tuple[str, ...]:
    """``all``, ``class/<name>`` per movable class and ``behaviour/<name>`` per behaviour."""
    classes = tuple(f"class/{OCC3D_CLASSES[c]}" for c in MOVABLE_CLASS_IDS)
    return ("all", *classes, *(f"behaviour/{b}" for b in BEHAVIOURS))


def empty_motion_stats(steps: int, device, prefix: str = "") -> dict[str, torch.Tensor]:
    """Zero ``<prefix>motion/<method>/<group>/err_sum`` and ``.../count``, [S] float64 each."""
    out = {}
    for m in MOTION_METHODS:
        for g in motion_groups():
            for k in ("err_sum", "count"):
                out[f"{prefix}motion/{m}/{g}/{k}"] = torch.zeros(
                    steps, dtype=torch.float64, device=device
                )
    return out


def _object_cv(occ: np.ndarray, poses: np.ndarray, tracks: list[MoverTrack], grid: GridSpec,
               steps: int) -> np.ndarray:  # fmt: skip
    """[N, S, 2] displacements of the object-CV rule for the tracks (their components)."""
    h = occ.shape[0]
    comps = [(tr.cls, tr.cells, tr.centroid) for tr in tracks]
    past = bev_components(occ[h - 1 - _LAG], grid)
    vel = object_velocities(comps, past, poses[h - 1 - _LAG], _LAG * KEYFRAME_DT, grid)
    t = np.arange(1, steps + 1) * KEYFRAME_DT
    return t[None, :, None] * vel[:, None, :] if len(tracks) else np.zeros((0, steps, 2))


def _model(model, occ, poses, tracks, grid, steps) -> np.ndarray:
    movers = getattr(model, "movers", "static")
    if movers == "learned":
        return head_displacements(model.mover_head, occ[-1], poses, tracks, grid, steps)
    if movers == "object_cv":
        return _object_cv(occ, poses, tracks, grid, steps)
    return np.zeros((len(tracks), steps, 2))


def add_motion_stats(
    stats: dict[str, torch.Tensor],
    model,
    batch: Mapping,
    inputs: str,
    history: int,
    grid: GridSpec,
    prefix: str = "",
) -> None:
    """Add a batch's moving movers' displacement errors (module docstring) to ``stats``.

    Args:
        stats: from :func:`empty_motion_stats`.
        model: the pose-warp model (its movers).
        batch: a collated batch of world-model windows (the setting's history occupancy,
            ``history_poses``, current and future boxes, ``meta.scene_description``).
        inputs: batch key of the setting's history occupancy.
        history: H; grid: the occupancy grid; prefix: the setting's metric prefix.
    """
    occ = batch[inputs][:, :history].cpu().numpy()
    poses = batch["history_poses"].double().cpu().numpy()
    names = ("current_boxes", "current_boxes_mask", "future_boxes", "future_boxes_mask")
    boxes = [batch[k].cpu().numpy() for k in names]
    steps = boxes[2].shape[1]
    descriptions = batch["meta"].get("scene_description", [""] * occ.shape[0])
    for i in range(occ.shape[0]):
        tracks = track_movers(occ[i], poses[i], grid)
        if not tracks:
            continue
        gt, valid, _ = mover_targets(tracks, *(b[i] for b in boxes))
        moving = valid[:, -1] & (np.hypot(*gt[:, -1].T) >= MOVING_M)
        if not moving.any():
            continue
        preds = {
            "model": _model(model, occ[i], poses[i], tracks, grid, steps),
            "object_cv": _object_cv(occ[i], poses[i], tracks, grid, steps),
        }
        behaviour = behaviour_of(descriptions[i])
        for m, pred in preds.items():
            err = np.hypot(*(pred - gt).transpose(2, 0, 1))  # [N, S]
            for j in np.flatnonzero(moving):
                groups = ["all", f"class/{OCC3D_CLASSES[tracks[j].cls]}"]
                groups += [f"behaviour/{behaviour}"] if behaviour else []
                e = torch.from_numpy(np.where(valid[j], err[j], 0.0))
                n = torch.from_numpy(valid[j].astype(np.float64))
                for g in groups:
                    key = f"{prefix}motion/{m}/{g}"
                    stats[f"{key}/err_sum"] += e.to(stats[f"{key}/err_sum"])
                    stats[f"{key}/count"] += n.to(stats[f"{key}/count"])


def motion_from_stats(
    stats: Mapping[str, torch.Tensor], horizons_s: tuple[float, ...], prefix: str = ""
) -> dict[str, float]:
    """``<prefix>motion/<method>/<group>/{ade,fde}_<h>`` (metres) and ``.../movers_<h>``
    (moving movers annotated at h's step) of every group with movers."""
    out: dict[str, float] = {}
    for m in MOTION_METHODS:
        for g in motion_groups():
            key = f"{prefix}motion/{m}/{g}"
            if f"{key}/err_sum" not in stats:
                continue
            e = stats[f"{key}/err_sum"].detach().cpu().double().numpy()
            n = stats[f"{key}/count"].detach().cpu().double().numpy()
            if not n.any():
                continue
            for h in horizons_s:
                k = int(round(h / KEYFRAME_DT))
                out[f"{key}/fde_{h:g}s"] = float(e[k - 1] / n[k - 1]) if n[k - 1] else float("nan")
                ade_n = n[:k].sum()
                out[f"{key}/ade_{h:g}s"] = float(e[:k].sum() / ade_n) if ade_n else float("nan")
                out[f"{key}/movers_{h:g}s"] = float(n[k - 1])
    return out


def motion_table(metrics: Mapping[str, float], horizons_s: tuple[float, ...],
                 prefix: str = "") -> str:  # fmt: skip
    """Markdown table: per group, each method's ADE / FDE at each horizon and the movers
    counted at the last horizon; "" when the metrics hold none."""
    hs = [f"{h:g}s" for h in horizons_s]
    rows = []
    for g in motion_groups():
        cells = []
        for m in MOTION_METHODS:
            key = f"{prefix}motion/{m}/{g}"
            for k in ("val/", ""):
                if f"{k}{key}/fde_{hs[-1]}" in metrics:
                    vals = [metrics[f"{k}{key}/{w}_{h}"] for w in ("ade", "fde") for h in hs]
                    n = int(metrics[f"{k}{key}/movers_{hs[-1]}"])
                    cells.append(" / ".join(f"{v:.2f}" for v in vals))
                    break
        if len(cells) == len(MOTION_METHODS):
            rows.append(f"| {g} | {n} | " + " | ".join(cells) + " |")
    if not rows:
        return ""
    what = " / ".join(f"ADE {h}" for h in hs) + " / " + " / ".join(f"FDE {h}" for h in hs)
    head = (
        "| group | moving movers at "
        + hs[-1]
        + " | "
        + " | ".join(f"{m} ({what}, m)" for m in MOTION_METHODS)
        + " |"
    )
    return "\n".join([head, "|---|---:|" + "---|" * len(MOTION_METHODS), *rows]) + "\n"


def write_motion(
    metrics: Mapping[str, float],
    run_dir: str | Path,
    horizons_s: tuple[float, ...],
    settings: Sequence[tuple[str, str]],
) -> str:
    """Write ``world_model_motion.csv`` into ``run_dir`` (one row per setting, method and
    group) and return the markdown section of the motion tables ("" when there are none)."""
    hs = [f"{h:g}s" for h in horizons_s]
    rows, md = [], []
    for label, prefix in settings:
        table = motion_table(metrics, horizons_s, prefix)
        if table:
            md += [
                f"\nMotion of moving road users ({label}): ADE / FDE of their centres, metres "
                f"(moving: their box moves >= {MOVING_M:g} m by the last step).\n\n",
                table,
            ]
        for m in MOTION_METHODS:
            for g in motion_groups():
                key = f"{prefix}motion/{m}/{g}"
                pick = next((k for k in ("val/", "") if f"{k}{key}/fde_{hs[-1]}" in metrics), None)
                if pick is None:
                    continue
                vals = [metrics[f"{pick}{key}/{w}_{h}"] for w in ("ade", "fde") for h in hs]
                rows.append([label, m, g, *vals, int(metrics[f"{pick}{key}/movers_{hs[-1]}"])])
    if rows:
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        with open(run_dir / "world_model_motion.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["setting", "method", "group", *(f"ade_{h}_m" for h in hs),
                        *(f"fde_{h}_m" for h in hs), f"movers_{hs[-1]}"])  # fmt: skip
            w.writerows(rows)
    return "".join(md)
