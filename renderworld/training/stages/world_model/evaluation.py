"""Evaluation statistics and report of the ``world_model`` stage.

The metrics are exactly :mod:`renderworld.metrics`': a rank accumulates counts over its shard
(per-step forecast confusions counted on the device by
:func:`~renderworld.metrics.occupancy.confusion_counts`, the counting rule that
:class:`~renderworld.metrics.ForecastMetric` uses too, label check included; a
:class:`~renderworld.metrics.PlanningMetric` per planner, flattened by
:func:`planning_to_stats`) into float64 tensors the loop sums over ranks; ``*_from_stats``
rebuild the accumulators from the summed counts and call their ``compute()``. Sums of counts are
exact, so a sharded evaluation equals the single-process one.

Methods (docs/protocol.md#baselines-and-references): ``model`` (forecast + plan; it reads the
command, which the infos derive from the GT future), ``model_history_command`` (the same model
given the command derived from the constant-turn-rate extrapolation of the history instead: no
input reads the future), ``copy_paste`` (current frame repeated), ``warp_cv`` / ``warp_ctr``
(current frame warped under constant velocity / constant turn rate), ``warp_object_cv``
(CTR-warp with each movable object moved at its own history velocity), ``cv_traj`` /
``ctr_traj`` (the same motion models as trajectories; history only) and the references
(:mod:`renderworld.training.stages.world_model.references`; they read the future):
``warp_gt_pose`` (current frame warped along the ground-truth future poses, an upper bound for
a static world), ``warp_gt_object_cv`` (the same with the movers moved by the object-CV rule:
the pose-warp design with perfect ego poses) and ``warp_gt_movers`` (the ground-truth future
movers pasted in).

Beside the whole split, forecasts and L2 are counted on a straight / turning split of the
windows (:func:`turning_windows`) and per class (CSV).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from renderworld.constants import FREE_ID, KEYFRAME_DT, NUM_OCC3D_CLASSES, OCC3D_CLASSES, GridSpec
from renderworld.metrics import FORECAST_HORIZONS_S, ForecastMetric, PlanningMetric
from renderworld.metrics.occupancy import iou_per_class
from renderworld.training.stages.common import confusion_stats
from renderworld.training.stages.world_model.heading import heading_from_stats
from renderworld.training.stages.world_model.report import (
    METHODS,
    REPORT_BASENAME,
    SPLITS,
    report_tables,
    write_report,
)
from renderworld.training.stages.world_model.splits import (
    TURN_THRESHOLD_DEG,
    add_split_l2,
    split_l2_from_stats,
    turning_windows,
)
from renderworld.training.stages.world_model.splits import horizon_name as _hname

__all__ = [
    "METHODS",
    "FORECASTERS",
    "PLANNERS",
    "empty_forecast_stats",
    "add_forecast_stats",
    "update_planning",
    "REPORT_BASENAME",
    "horizons_for",
    "setting_metrics",
    "forecast_to_stats",
    "forecast_from_stats",
    "planning_to_stats",
    "planning_from_stats",
    "report_tables",
    "SPLITS",
    "TURN_THRESHOLD_DEG",
    "turning_windows",
    "add_split_l2",
    "split_l2_from_stats",
    "write_report",
]

FORECASTERS = tuple(m[0] for m in METHODS if m[2])
PLANNERS = tuple(m[0] for m in METHODS if m[3])
#: Rows that read no model (baselines and references): their figures never change in a run.
MODEL_FREE_METHODS = (
    "copy_paste", "warp_cv", "warp_ctr", "warp_object_cv", "cv_traj", "ctr_traj",
    "warp_gt_pose", "warp_gt_object_cv", "warp_gt_movers",
)  # fmt: skip
_COLL_KEYS = ("hit", "evaluated", "gt_skipped", "outside")


def horizons_for(future: int) -> tuple[float, ...]:
    """Reported horizons (s) for ``future`` rolled-out frames: 1/2/3 s where they exist.

    With fewer than 2 future frames (no whole second) the last frame's time is reported.
    """
    hs = tuple(h for h in FORECAST_HORIZONS_S if round(h / KEYFRAME_DT) <= future)
    return hs or (future * KEYFRAME_DT,)


def _f64(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


# ------------------------------------------------------------------------ forecast
def forecast_to_stats(
    pred: torch.Tensor,
    gt: torch.Tensor,
    valid: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-step confusion counts of a batch of forecasts, on their device.

    The counts are those of :class:`~renderworld.metrics.ForecastMetric` (18x18, rows = GT,
    frames with ``valid`` False left out and counted), computed with ``torch.bincount`` so
    they stay on the accelerator.

    Args:
        pred: [B, S, X, Y, Z] integer labels of frames t+1..t+S.
        gt: same shape, ground truth.
        valid: [B, S] bool.
        mask: optional [B, S, X, Y, Z] bool region.

    Returns:
        (confusion [S, 18, 18] float64, skipped frames [] float64).
    """
    if pred.shape != gt.shape or pred.dim() != 5 or tuple(valid.shape) != tuple(pred.shape[:2]):
        raise ValueError(
            f"pred/gt/valid: expected [B, S, X, Y, Z] x2 and [B, S], got {tuple(pred.shape)}, "
            f"{tuple(gt.shape)}, {tuple(valid.shape)}"
        )
    steps = [
        confusion_stats(
            pred[valid[:, s], s], gt[valid[:, s], s], None if mask is None else mask[valid[:, s], s]
        )
        for s in range(pred.shape[1])
    ]
    return torch.stack(steps), (~valid).sum().double()


def empty_forecast_stats(
    steps: int, device: torch.device, prefix: str = "", methods: tuple[str, ...] | None = None
) -> dict[str, torch.Tensor]:
    """Zero ``<prefix><method>/<region>/confusion`` [S, 18, 18] and ``.../skipped`` [].

    Regions: ``full``, ``cam`` (camera mask) and the full volume of the ``straight`` /
    ``turning`` windows. ``methods``: the forecasters evaluated (default all of ``METHODS``).
    """
    out = {}
    for p in FORECASTERS if methods is None else methods:
        for region in ("full", "cam", *SPLITS):
            out[f"{prefix}{p}/{region}/confusion"] = torch.zeros(
                steps, NUM_OCC3D_CLASSES, NUM_OCC3D_CLASSES, dtype=torch.float64, device=device
            )
            out[f"{prefix}{p}/{region}/skipped"] = torch.zeros(
                (), dtype=torch.float64, device=device
            )
    return out


def add_forecast_stats(
    stats: dict[str, torch.Tensor],
    forecasts: Mapping[str, torch.Tensor],
    gt: torch.Tensor,
    mask_camera: torch.Tensor,
    valid: torch.Tensor,
    prefix: str = "",
    turning: torch.Tensor | None = None,
) -> None:
    """Add each method's [B, S, X, Y, Z] forecast to its full-volume and camera-mask counts.

    Keys are ``<prefix><method>/...`` (see :func:`empty_forecast_stats`). With ``turning``
    ([B] bool, :func:`turning_windows`) the full-volume counts of the straight and the turning
    windows are added too.
    """
    regions = [("full", None, valid), ("cam", mask_camera, valid)]
    if turning is not None:
        t = turning.to(valid.device).bool()[:, None]
        regions += [("straight", None, valid & ~t), ("turning", None, valid & t)]
    for p, pred in forecasts.items():
        for region, mask, ok in regions:
            if region in SPLITS and not ok.any():
                continue  # no window of that kind in this batch
            conf, skipped = forecast_to_stats(pred, gt, ok, mask)
            if region in SPLITS:
                skipped = skipped * 0  # the other split's frames are not skipped
            for name, value in (("confusion", conf), ("skipped", skipped)):
                key = f"{prefix}{p}/{region}/{name}"
                stats[key] += value.to(stats[key].device)


def forecast_from_stats(
    stats: Mapping[str, torch.Tensor],
    key: str,
    horizons_s: tuple[float, ...],
    mask_name: str | None = None,
) -> dict[str, float]:
    """Forecast metrics of rank-summed counts (see :func:`forecast_to_stats`).

    Returns:
        ``miou_<h>``, ``miou_avg``, ``iou_<h>``, ``iou_avg``, ``movers_miou_<h>``,
        ``movers_miou_avg`` (h = ``1s``...) and per step ``miou_step<k>``, ``iou_step<k>``,
        ``movers_miou_step<k>`` (k = 1..S), as fractions.
    """
    conf = stats[f"{key}/confusion"].detach().cpu().double().numpy()
    metric = ForecastMetric(steps=conf.shape[0], horizons_s=horizons_s, mask_name=mask_name)
    for step, c in zip(metric.per_step, conf):
        step.confusion = np.rint(c).astype(np.int64)
    metric.skipped_frames = int(round(float(stats[f"{key}/skipped"])))
    res = metric.compute()
    out: dict[str, float] = {}
    for name in ("miou", "iou", "movers_miou"):
        for h in metric.horizons_s:
            out[f"{name}_{_hname(h)}"] = float(res[f"{name}@{h:g}s"])
        out[f"{name}_avg"] = float(res[f"{name}_avg"])
        for k, v in enumerate(res[f"{name}_per_step"], start=1):
            out[f"{name}_step{k}"] = float(v)
    for h, k in zip(metric.horizons_s, metric.horizon_steps):
        ious = iou_per_class(np.rint(conf[k - 1]).astype(np.int64))
        for c, name in enumerate(OCC3D_CLASSES[:FREE_ID]):
            out[f"class_iou/{name}_{_hname(h)}"] = float(ious[c])
    return out


# ------------------------------------------------------------------------ planning
def planning_to_stats(metric: PlanningMetric, key: str) -> dict[str, torch.Tensor]:
    """Float64 counts of ``metric``: L2 error sums/counts per step and collision counts."""
    out = {
        f"{key}/err_sum": _f64(metric.err_sum),
        f"{key}/err_count": _f64(metric.err_count),
        f"{key}/masked_steps": _f64(metric.masked_steps),
        f"{key}/num_samples": _f64(metric.num_samples),
    }
    for src in PlanningMetric.SOURCES:  # zeros when never updated (an empty shard)
        for k in _COLL_KEYS:
            out[f"{key}/{src}_{k}"] = _f64(metric.coll[src][k])
    return out


def update_planning(
    plan: Mapping[str, PlanningMetric],
    trajectories: Mapping[str, torch.Tensor],
    batch: Mapping,
    future_occ: torch.Tensor,
    valid: torch.Tensor,
) -> None:
    """Add each planner's [B, S, 2] trajectory vs a batch's GT (trajectory, boxes, occupancy).

    Uses ``future_traj``, ``future_boxes`` (x, y, length, width, yaw columns),
    ``future_boxes_mask`` and ``future_poses`` of the batch; ``future_occ`` [B, S, X, Y, Z].
    """
    boxes = batch["future_boxes"][..., :5].cpu().numpy()
    boxes_ok = batch["future_boxes_mask"].cpu().numpy()
    poses = batch["future_poses"].cpu().numpy()
    occ = future_occ.cpu().numpy()
    for p, traj in trajectories.items():
        plan[p].update(
            traj.float(),
            batch["future_traj"].float(),
            valid=valid.cpu(),
            agent_boxes=list(boxes),
            agent_valid=list(boxes_ok),
            occupancy=occ,
            occupancy_poses=poses,
        )


def planning_from_stats(
    stats: Mapping[str, torch.Tensor],
    key: str,
    horizons_s: tuple[float, ...],
    grid: GridSpec,
) -> dict[str, float]:
    """Planning metrics of rank-summed counts (see :func:`planning_to_stats`).

    Returns:
        ``l2_at_horizon_<h>`` / ``l2_mean_to_horizon_<h>`` (+ ``_avg``) in metres,
        ``collision_<boxes|occupancy>_<at_horizon|mean_to_horizon>_<h>`` (+ ``_avg``) as
        fractions, ``collision_<source>_gt_skipped`` / ``_outside_grid`` counts.
    """

    def ints(name: str) -> np.ndarray:
        return np.rint(stats[f"{key}/{name}"].detach().cpu().double().numpy()).astype(np.int64)

    err_sum = stats[f"{key}/err_sum"].detach().cpu().double().numpy()
    metric = PlanningMetric(steps=len(err_sum), horizons_s=horizons_s, occupancy_grid=grid)
    metric.err_sum = err_sum.copy()
    metric.err_count = ints("err_count")
    metric.masked_steps = int(ints("masked_steps"))
    metric.num_samples = int(ints("num_samples"))
    for src in PlanningMetric.SOURCES:
        metric.sources_seen.add(src)
        for k in _COLL_KEYS:
            metric.coll[src][k] = ints(f"{src}_{k}")
    res = metric.compute()
    out: dict[str, float] = {}
    for name, value in res.items():
        if isinstance(value, (int, float)) and name not in ("num_samples", "masked_steps"):
            out[name.replace("@", "_")] = float(value)
    return out


def setting_metrics(
    stats: Mapping[str, torch.Tensor], prefix: str, horizons: tuple[float, ...], grid: GridSpec
) -> dict[str, float]:
    """Metrics of every method of one evaluated setting from the rank-summed statistics.

    Args:
        stats: the summed statistics of ``WorldModelStage.evaluate``.
        prefix: the setting's key prefix (``""`` for the run's own setting).
        horizons: the reported horizons (s), see :func:`horizons_for`.
        grid: the occupancy grid (collision vs GT occupancy).

    Returns:
        ``{"<prefix><method>/<metric>": value}``: forecast metrics (full volume, camera mask,
        straight / turning splits), planning L2 and collisions, and heading errors, for each
        row of :data:`METHODS` the statistics hold.
    """
    out: dict[str, float] = {}
    for m, _, has_occ, has_traj in METHODS:
        p = f"{prefix}{m}"
        if has_occ and f"{p}/full/confusion" not in stats:
            continue  # a variant of another forecaster
        if not has_occ and f"{p}/plan/err_sum" not in stats:
            continue  # a plan of another forecaster
        if has_occ:
            full = forecast_from_stats(stats, f"{p}/full", horizons)
            cam = forecast_from_stats(stats, f"{p}/cam", horizons, "camera")
            out.update({f"{p}/{k}": v for k, v in full.items()})
            out.update(
                {f"{p}/cam/{k}": v for k, v in cam.items() if "step" not in k and "class" not in k}
            )
        for split in SPLITS:
            if has_occ:
                res = forecast_from_stats(stats, f"{p}/{split}", horizons)
                out.update({f"{p}/{split}/{k}": v for k, v in res.items()
                            if "step" not in k and "class_iou" not in k})  # fmt: skip
            if has_traj:
                res = split_l2_from_stats(stats, f"{p}/{split}", horizons)
                out.update({f"{p}/{split}/{k}": v for k, v in res.items()})
            elif has_occ:
                n = split_l2_from_stats(stats, f"{prefix}model/{split}", horizons)
                out[f"{p}/{split}/num_windows"] = n["num_windows"]
        if has_traj:
            res = planning_from_stats(stats, f"{p}/plan", horizons, grid)
            out.update({f"{p}/{k}": v for k, v in res.items()})
        if f"{p}/heading/count" in stats:
            res = heading_from_stats(stats, p, horizons)
            out.update({f"{p}/{k}": v for k, v in res.items()})
    return out
